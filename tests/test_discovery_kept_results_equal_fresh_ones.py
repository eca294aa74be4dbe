"""Discovery's per-unit bookkeeping, fifth round: what is now kept or taken another way gives
the numbers and decisions the former code gave.

- the term columns of a term set and the balanced grid's group matrices are kept on the grid
  (read-only) and equal a fresh computation;
- lack-of-fit tests are kept per discovery (selection and the report ask for the same ones):
  equal to a fresh test, the caller's dict is its own;
- the noise pooling in Python floats equals the former per-entry numpy arithmetic;
- the rank shortcut's held-out folds, taken with one index array, are the matrices
  ``np.delete`` gave;
- ``to_jsonable`` of a numpy float64 is what it was.
"""

from __future__ import annotations

import math

import numpy as np

from calib_core.discovery import design, fit
from calib_core.discovery import turntable as disc
from calib_core.discovery.noise import NoiseModel
from calib_core.discovery.replay import MIN_POOL_DOF
from calib_core.effects import CHANNELS
from calib_core.results import to_jsonable

from conftest import discovery_unit as _unit  # a simulated unit's sessions


def test_term_columns_are_kept_per_grid_and_read_only():
    d = disc._Discovery(_unit(1, n_reps=4), 0.01)
    g = d.g
    names = tuple(sorted(g.offset))
    for key in ((), names[:1], names[1:3], names):
        cols = g.cols(key)
        fresh = np.concatenate([np.arange(*g.offset[n]) for n in key]) if key else np.zeros(0, np.int64)
        assert cols.dtype == fresh.dtype and np.array_equal(cols, fresh)
        assert g.cols(key) is cols and not cols.flags.writeable


def test_balanced_group_matrices_equal_a_fresh_build():
    d = disc._Discovery(_unit(2, n_reps=4), 0.01)
    g = d.g
    assert g.balanced
    gcode, G, cnt, grp, dof = g._balanced_groups()
    ref = np.zeros((g.n, len(g.groups)))
    ref[np.arange(g.n), g.gcode[0]] = 1.0
    np.testing.assert_array_equal(G, ref)
    np.testing.assert_array_equal(cnt, ref.sum(axis=0))
    np.testing.assert_array_equal(grp, np.tile(g.gcode[0], g.R))
    np.testing.assert_array_equal(dof, ((ref.sum(axis=0) - 1) * (g.R - 1)).astype(np.int64))
    assert not G.flags.writeable
    # two_way hands out its own dof (callers keep it) and the same rows as before
    X = np.random.default_rng(0).normal(size=(2, g.R, g.n, 3))
    e1, grp1, dof1 = g.two_way(X)
    dof1[:] = -1
    e2, _, dof2 = g.two_way(X)
    np.testing.assert_array_equal(e1, e2)
    np.testing.assert_array_equal(dof2, dof)


def test_lack_of_fit_tests_are_kept_and_equal_fresh_ones():
    d = disc._Discovery(_unit(3, n_reps=4), 0.01)
    name = sorted(d.g.offset)[0]
    for names in ((), (name,)):
        first = d.channel_lack_of_fit(names, 0.01 / 6)
        assert first == d._channel_lack_of_fit(names, 0.01 / 6)
        first["gx"] = None  # the caller's dict: the kept one is untouched
        assert d.channel_lack_of_fit(names, 0.01 / 6)["gx"] is not None
        assert d.lack_of_fit(names, 0.01) == d._lack_of_fit(names, 0.01)
        assert d.lack_of_fit(names, 0.01) is d.lack_of_fit(tuple(reversed(names)), 0.01)
    # another threshold is another test
    assert d.lack_of_fit((), 0.5).threshold == 0.5


def _former_pooling(ss, w2, dof, groups):
    """The per-entry arithmetic of the former _noise (numpy scalars)."""
    rows, inst = [], np.zeros(ss.shape)
    for c, ch in enumerate(CHANNELS):
        pooled_ss, pooled_dof = 0.0, 0
        for gi in range(ss.shape[1]):
            pooled_ss += float(ss[c, gi])
            pooled_dof += int(dof[gi])
        pooled_var = pooled_ss / pooled_dof if pooled_dof else np.nan
        for gi, gname in enumerate(groups):
            wsd = float(np.sqrt(w2[c, gi]))
            var = float(ss[c, gi]) / int(dof[gi]) if dof[gi] >= MIN_POOL_DOF else pooled_var
            step_sd = float(np.sqrt(var)) if np.isfinite(var) else wsd
            inst[c, gi] = float(np.sqrt(max(step_sd**2 - wsd**2, 0.0)))
            rows.append((ch, gname, int(dof[gi]), step_sd, wsd, inst[c, gi]))
    return rows, inst


def test_noise_pooling_equals_the_former_arithmetic(monkeypatch):
    d = disc._Discovery(_unit(4, n_reps=4), 0.01)
    g = d.g
    rng = np.random.default_rng(5)
    K = np.tile(np.eye(3), (2, 1)) * (1 + 1e-3 * rng.normal(size=(6, 3)))
    resid = rng.normal(size=(g.R, g.n, 6)) * 1e-2
    for dof_override in (None, "small", "zero"):
        if dof_override is not None:  # groups below MIN_POOL_DOF borrow the pooled value
            e, grp, dof = design.UnitGrid.two_way(g, resid)
            dof = dof.copy()
            dof[0] = 3 if dof_override == "small" else 0
            if dof_override == "zero":
                dof[:] = 0
            monkeypatch.setattr(design.UnitGrid, "two_way", lambda self, X, _r=(e, grp, dof): _r)
        noise = NoiseModel.from_residuals(g, K, resid)
        rows, sigma = noise.rows, noise.sigma
        e, grp, dof = g.two_way(resid)
        white = g.white_sigma(K)
        ng = len(g.groups)
        ss = np.zeros((6, ng))
        w2 = np.zeros((6, ng))
        for gi in range(ng):
            ss[:, gi] = np.sum(e[grp == gi] ** 2, axis=0)
            w2[:, gi] = np.mean(white[g.gcode == gi] ** 2, axis=0)
        ref_rows, inst = _former_pooling(ss, w2, dof, g.groups)
        assert len(rows) == len(ref_rows)
        for r, q in zip(rows, ref_rows):
            assert [type(x) for x in r] == [type(x) for x in q]
            assert all(x == y or (x != x and y != y) for x, y in zip(r, q))
        inst_row = np.where(g.real[..., None], inst.T[np.maximum(g.gcode, 0)], 0.0)
        ref_sigma = np.sqrt(white**2 + np.nan_to_num(inst_row) ** 2)
        ref_sigma[~g.real] = 1.0
        np.testing.assert_array_equal(sigma, ref_sigma)
        monkeypatch.undo()


def test_rank_shortcut_folds_are_the_deleted_matrices(monkeypatch):
    seen = []
    real_cholesky = np.linalg.cholesky

    def spy(a):
        seen.append(np.array(a))
        return real_cholesky(a)

    for R in (2, 3, 5):
        rng = np.random.default_rng(R)
        D = rng.normal(size=(6, R, 7, 4))
        seen.clear()
        monkeypatch.setattr(np.linalg, "cholesky", spy)
        fit._surely_full_rank(D)
        monkeypatch.undo()
        # the folds as the former code built them
        G = D.swapaxes(-1, -2) @ D
        included = np.ones((R + 1, R))
        included[np.arange(1, R + 1), np.arange(R)] = 0.0
        full = np.zeros((6, R + 1, 3 + R, 3 + R))
        full[:, :, :3, :3] = np.einsum("fr,crij->cfij", included, G[:, :, :3, :3])
        for r in range(R):
            full[:, :, :3, 3 + r] = full[:, :, 3 + r, :3] = G[:, None, r, :3, 3]
            full[:, :, 3 + r, 3 + r] = G[:, None, r, 3, 3]
        folds = [
            np.delete(np.delete(full[:, 1 + h : 2 + h], 3 + h, axis=-1), 3 + h, axis=-2) for h in range(R)
        ]
        held_out = np.concatenate(folds, axis=1)
        tr = np.trace(held_out, axis1=-2, axis2=-1)
        expected = held_out - (fit.RANK_SURE_RATIO * tr)[..., None, None] * np.eye(2 + R)
        assert len(seen) == 2  # fold 0, then the held-out folds
        np.testing.assert_array_equal(seen[1], expected)


def test_to_jsonable_of_numpy_floats():
    for v in (
        np.float64(1.5),
        np.float64(-0.0),
        np.float64("nan"),
        np.float64("inf"),
        np.float32(2.5),
        3.25,
        float("nan"),
    ):
        got = to_jsonable(v)
        expected = float(v) if math.isfinite(float(v)) else None
        assert type(got) is type(expected) and (got == expected or got is expected)
    assert to_jsonable({"a": [np.float64(1.0), np.float64("nan")]}) == {"a": [1.0, None]}
