"""Shortcuts of the discovery set-up (issue 7, fourth round) against the work they skip.

- the grid's protocol part (:func:`calib_core.discovery.design.protocol_layout`) is read-only, and
  a unit whose steps differ gets a layout of its own;
- the rank test is skipped when every fold is far from losing rank
  (:func:`calib_core.discovery.fit._surely_full_rank`): it never skips a design that the exact
  test (numpy's matrix_rank rule) finds deficient;
- the covariance of a fit is built on first use, with the formula it had.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from calib_core.discovery import design, diagnose_unit, fit
from calib_core.effects import catalogue
from calib_core.errors import DesignError
from calib_core.linalg import PINV_RCOND, lstsq_pinv_cov, qr_r
from calib_core.sim import protocols

from conftest import discovery_unit as _unit  # a simulated unit's sessions

STEPS = protocols.default_session()


def _grid_fields(g: design.UnitGrid) -> dict:
    return {f.name: getattr(g, f.name) for f in dataclasses.fields(g)}


def _assert_same(a, b):
    if isinstance(a, np.ndarray):
        assert a.dtype == b.dtype and a.shape == b.shape
        np.testing.assert_array_equal(a, b)
    elif isinstance(a, (list, tuple)):
        assert len(a) == len(b)
        for x, y in zip(a, b):
            _assert_same(x, y)
    else:
        assert a == b


def test_the_layout_arrays_are_read_only_and_the_units_own_columns_are_not():
    grid = design.UnitGrid.build(_unit(1, unit="U001"), sorted(catalogue()))
    assert not grid.real.flags.writeable and not grid.y.flags.writeable
    with pytest.raises(ValueError):
        grid.gcode[0, 0] = 1
    assert grid.M.flags.writeable  # the unit's own copy (raw columns filled in)


def test_a_unit_whose_steps_differ_gets_its_own_layout():
    names = sorted(catalogue())
    sessions = _unit(3)
    keep = np.ones(len(sessions[1]), bool)
    keep[[5, 50]] = False
    dropped = list(sessions)
    dropped[1] = sessions[1].select(keep)
    a = design.UnitGrid.build(sessions, names)
    b = design.UnitGrid.build(dropped, names)
    assert a.balanced and not b.balanced
    assert b.real[1].sum() == len(sessions[1]) - 2


def _exact_full_rank(D: np.ndarray) -> bool:
    """_check_rank's exact test: numpy's matrix_rank rule on every channel and fold."""
    C, R = D.shape[:2]
    R4 = qr_r(D)
    Y = np.zeros((C, R + 1, R, 4, 3 + R))
    Y[..., :3] = R4[:, None, :, :, :3]
    for r in range(R):
        Y[:, :, r, :, 3 + r] = R4[:, None, r, :, 3]
    Y[:, np.arange(1, R + 1), np.arange(R)] = 0.0
    s = np.linalg.svd(Y.reshape(C, R + 1, 4 * R, 3 + R), compute_uv=False)
    rows = (D[0, :, :, 3] != 0).sum(axis=1)
    n_rows = np.array([rows.sum()] + [rows.sum() - rows[h] for h in range(R)])
    n_cols = np.array([3 + R] + [3 + R - 1] * R)
    tol = s.max(axis=-1) * np.maximum(n_rows, n_cols) * np.finfo(float).eps
    return bool(((s > tol[..., None]).sum(axis=-1) >= n_cols).all())


def test_rank_shortcut_never_skips_a_deficient_design():
    rng = np.random.default_rng(20261122)
    certified = deficient = 0
    for trial in range(1200):
        R, n = int(rng.integers(2, 6)), int(rng.integers(3, 40))
        raw = rng.normal(size=(6, R, n, 3)) * 10.0 ** rng.uniform(-1, 1, size=(6, 1, 1, 3))
        kind = trial % 4
        if kind == 1:  # a raw column constant within each repetition: a copy of the biases
            raw[:, :, :, 1] = rng.normal(size=(6, R, 1))
        elif kind == 2:  # nearly so
            raw[:, :, :, 1] = rng.normal(size=(6, R, 1)) + 10.0 ** rng.uniform(-13, -3) * rng.normal(
                size=(6, R, n)
            )
        elif kind == 3:  # two raw columns nearly collinear
            raw[:, :, :, 2] = 3.0 * raw[:, :, :, 0] + 10.0 ** rng.uniform(-14, -1) * rng.normal(
                size=(6, R, n)
            )
        w = 10.0 ** rng.uniform(-1, 1, size=(6, R, n, 1))
        if trial % 3 == 0:
            w[:, :, rng.integers(1, n) :] = 0.0  # padding rows (weight 0)
        D = np.concatenate([w * raw, w], axis=-1)
        sure, exact = fit._surely_full_rank(D), _exact_full_rank(D)
        assert not (sure and not exact), trial
        certified += sure
        deficient += not exact
    # both cases occur (the test can tell a shortcut that never or always fires)
    assert certified > 100 and deficient > 100


def test_rank_shortcut_takes_a_real_unit_and_the_exact_error_stays():
    sessions = _unit(5)
    d = fit.joint_model(sessions)
    w = np.moveaxis(d.weight, -1, 0)[..., None]
    assert fit._surely_full_rank(np.concatenate([w * d.g.M[..., :3], w], axis=-1))
    for sm in sessions:  # gy constant within each repetition: the exact test's error
        sm.gyro[:, 1] = 1.0 + sm.key.rep
    with pytest.raises(DesignError) as err:
        diagnose_unit(sessions, tables=False)
    assert err.value.code == "E_DISCOVERY_RANK" and "rank 5 < 6" in str(err.value)


def test_lazy_covariance_is_the_svd_formula():
    rng = np.random.default_rng(6)
    for p, deficient in ((4, False), (5, True)):
        Z = rng.normal(size=(20, p)) * np.array([1.0, 1e3, 1e-2, 5.0, 1.0][:p])
        if deficient:
            Z[:, 4] = 2.0 * Z[:, 0]
            Z[:, 3] = 0.0
        y = rng.normal(size=20)
        theta, cov, rank = lstsq_pinv_cov(Z, y)
        # the formula, spelled out
        norms = np.linalg.norm(Z, axis=0)
        live = norms > 1e-12 * norms.max()
        scale = np.where(live, norms, 1.0)
        U, s, Vt = np.linalg.svd(Z / scale, full_matrices=False)
        keep = (s > PINV_RCOND**0.5 * s[0]) & (s > 0)
        inv_s = np.where(keep, 1.0 / np.where(keep, s, 1.0), 0.0)
        ref = (Vt.T * inv_s**2) @ Vt / np.outer(scale, scale)
        undetermined = (np.abs(Vt[~keep]) > 1e-6).any(axis=0) | ~live
        ref[undetermined, :] = np.nan
        ref[:, undetermined] = np.nan
        np.testing.assert_array_equal(cov, ref)
        assert rank == int(keep.sum()) == (p - 2 if deficient else p)
        assert (theta[~live] == 0).all()
