"""Discovery's speed work of issue 32, round 3, against the work it skips, bit for bit:

- a term's fit alone on the fold of all repetitions takes the factorisation the
  undetermined test made of the same columns (:func:`calib_core.linalg.pinv_theta`): the
  same coefficients and rank as a fresh :func:`calib_core.linalg.lstsq_pinv`;
- identifiability takes that factorisation too (``analyse(..., svds=...)``): the same
  result as factorising the terms itself;
- the terms' regressors laid out channel by channel in memory: the same numbers as the
  sensing geometry's product on the terms' columns side by side;
- the stacked Satterthwaite factors and Box's epsilon over blocks of one shape: the same
  numbers as the plain formulas block by block.
"""

from __future__ import annotations

import numpy as np

from calib_core.discovery import identifiability as ident
from calib_core.discovery import noise
from calib_core.discovery.design import _body_regressors, _joint_context
from calib_core.discovery.turntable import _Discovery
from calib_core.effects import get_effect
from calib_core.linalg import lstsq_pinv, pinv_solutions, pinv_theta

from conftest import discovery_unit as _unit  # a simulated unit's sessions


def test_a_kept_factorisation_solves_as_a_fresh_one():
    rng = np.random.default_rng(5)
    Zs = [rng.normal(size=(30, p)) for p in (3, 6, 3, 9)]
    Zs[1][:, 2] = 0.0  # a dead column
    Zs[3][:, 4] = Zs[3][:, 0]  # an undetermined direction
    y = rng.normal(size=30)
    for Z, sol in zip(Zs, pinv_solutions(Zs)):
        theta, rank, _ = lstsq_pinv(Z, y)
        kept_theta, kept_rank = pinv_theta(sol, y)
        np.testing.assert_array_equal(kept_theta, theta)
        assert kept_rank == rank


def test_the_unit_fits_and_identifiability_with_kept_factorisations_equal_fresh_ones():
    d = _Discovery(_unit(3, n_reps=4), 0.01)
    m = d.model
    P = m.g.P
    reused = [n for n in m.names if tuple(m.g.cols((n,)).tolist()) in m._term_solutions]
    assert reused  # the shortcut is taken on a typical unit
    for name in reused:
        cols = m.g.cols((name,))
        theta, rank, _ = lstsq_pinv(m.Rg0[:P, cols], m.Rg0[:P, P])
        f = m.fit((name,))
        np.testing.assert_array_equal(f.theta, theta)
        assert f.rank == rank
    terms, pnames = {}, {}
    for n, keep in d.policy._determined_columns().items():
        if keep:
            terms[n] = m.Rg0[:P, keep]
            pnames[n] = tuple(get_effect(n).param_names[k - m.g.offset[n][0]] for k in keep)
    assert d.policy.identifiability == ident.analyse(np.zeros((P, 0)), terms, pnames, 0.05)


def test_the_terms_regressors_channel_by_channel_equal_the_geometrys_product():
    d = _Discovery(_unit(4, n_reps=3), 0.01)
    m = d.model
    ctx = _joint_context(m.layout)
    terms = [get_effect(n) for n in m.names]
    E = np.concatenate([np.asarray(t.sensor_regressors(ctx, m.geometry), float) for t in terms], axis=-1)
    Z = _body_regressors(terms, ctx, m.geometry, E.shape[-1])
    np.testing.assert_array_equal(Z, -m.geometry.to_body(E))


def test_stacked_noise_factors_equal_the_plain_formulas():
    rng = np.random.default_rng(9)
    dev = rng.normal(size=(6, 4, 50)) * rng.uniform(0.5, 2.0, size=(6, 1, 50))
    dev[2] = 0.0  # a silent channel
    for c in range(6):  # dof_inflation's formula, one block
        d, (R, n) = dev[c], dev[c].shape
        v = np.sum(d**2, axis=0) / (R - 1)
        if not np.any(v > 0):
            plain = 1.0
        else:
            hetero = n * np.sum(v**2) * (R - 1) / (R + 1) / np.sum(v) ** 2
            rho2 = sum((np.sum(d[:, k:] * d[:, :-k]) / np.sum(d**2)) ** 2 for k in range(1, 6))
            plain = float(max(hetero, 1.0) * (1.0 + 2.0 * rho2))
        assert noise.dof_inflations(dev)[c] == plain == noise.dof_inflation(d)
    blocks = [rng.normal(size=(5, p)) for p in (3, 3, 2, 3, 1)]
    k = 4  # Box's epsilon, Huynh-Feldt's unbiased traces, block by block
    t1, t2, t1sq = [], 0.0, 0.0
    for b in blocks:
        S = b.T @ b / k
        tr = float(np.trace(S))
        t2_c = k * (k * float(np.sum(S * S)) - tr**2) / ((k - 1) * (k + 2))
        t1.append(tr)
        t2 += t2_c
        t1sq += tr**2 - 2.0 * t2_c / k
    t1sq += sum(t1) ** 2 - sum(x * x for x in t1)
    plain = float(np.clip(t1sq / (10 * t2), 1.0 / 10, 1.0))
    assert noise.sphericity_epsilon(blocks) == plain
