"""The fast discovery path (issue 7) against independent computations.

Discovery fits every term subset on every leave-one-repetition-out fold from small R
factors of each channel's bias-removed weighted design (:class:`calib_core.discovery.fit.JointModel`).
Here each of its numbers is recomputed the plain way, one dense weighted least squares over
every row with explicit bias columns, on balanced units and on units whose repetitions lost
steps (the general two-way path), and the noise estimate is recomputed with
:func:`calib_core.discovery.replay.estimate_noise_arrays`."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest

from calib_core.discovery import replay
from calib_core.discovery.noise import NoiseModel
from calib_core.discovery.replay import NoiseEstimate, estimate_noise_arrays, two_way_residual
from calib_core.discovery.turntable import _Discovery, diagnose_unit
from calib_core.effects import CHANNELS, MotionContext, get_effect
from calib_core.errors import DesignError
from calib_core.linalg import lstsq_pinv_cov, lstsq_pinv_stack
from calib_core.sim import protocols
from calib_core.sim import simulator as sim
from calib_core.sim.simulator import REALISTIC_NOISE, simulate_unit

STEPS = protocols.default_session()


def _unit(seed: int, effect: str | None, theta, n_reps: int = 3, drop: bool = False):
    rng = np.random.default_rng(seed)
    truth = sim.typical_truth(rng, **REALISTIC_NOISE, temperature=sim.TemperatureProfile())
    if effect:
        truth = truth.with_effects((get_effect(effect), np.asarray(theta, float)))
    sessions, _ = simulate_unit(truth, STEPS, rng, n_reps)
    if drop:  # two repetitions lose a few steps: unbalanced step x repetition tables
        for r, idx in ((0, [3, 40, 77]), (1, [10])):
            keep = np.ones(len(sessions[r]), bool)
            keep[idx] = False
            sessions[r] = sessions[r].select(keep)
    return sessions


def _long(d: _Discovery):
    """Every real row of the unit: (rep, step, channel, group, y, raw (3), weight, Z)."""
    rows = []
    for r, sm in enumerate(d.sessions):
        n = len(sm)
        ctx = MotionContext.from_refs(sm.w_ref, sm.f_ref, temp_c=sm.temp_c, t=sm.t_mid, g_local=sm.g_local)
        Z = -np.concatenate([get_effect(nm).regressors(ctx, d.geometry) for nm in d.names], axis=-1)
        y = np.hstack([sm.w_ref, sm.f_ref])
        for c in range(6):
            raw = sm.gyro if c < 3 else sm.accel
            rows.append(
                dict(
                    rep=np.full(n, r),
                    step=sm.step.astype(int),
                    channel=np.full(n, c),
                    group=np.array([replay.test_group(t) for t in sm.test]),
                    y=y[:, c],
                    raw=raw,
                    w=d.weight[r, :n, c],
                    Z=Z[:, c, :],
                )
            )
    return {k: np.concatenate([x[k] for x in rows]) for k in rows[0]}


def _dense_fit(L, train: np.ndarray, cols: np.ndarray, R: int):
    """Weighted least squares of y on [raw per channel | bias per (rep, channel) | Z_S]."""
    n = len(L["y"])
    X = np.zeros((n, 18 + 6 * R + len(cols)))
    for c in range(6):
        m = L["channel"] == c
        X[m, 3 * c : 3 * c + 3] = L["raw"][m]
    X[np.arange(n), 18 + 6 * L["rep"] + L["channel"]] = 1.0
    X[:, 18 + 6 * R :] = L["Z"][:, cols]
    keep_cols = np.flatnonzero(np.abs(X[train]).sum(axis=0) > 0)
    Xw = X[train][:, keep_cols] * L["w"][train, None]
    beta_k, *_ = np.linalg.lstsq(Xw, L["y"][train] * L["w"][train], rcond=None)
    beta = np.zeros(X.shape[1])
    beta[keep_cols] = beta_k
    K = beta[:18].reshape(6, 3)
    b = beta[18 : 18 + 6 * R].reshape(R, 6)
    theta = beta[18 + 6 * R :]
    return K, b, theta, X, beta


@pytest.mark.parametrize(
    "effect,theta,drop",
    [
        pytest.param(None, None, False, marks=pytest.mark.slow),
        pytest.param("gyro_g_sensitivity", [0, 0, 0, 0, 0, 0, 0.04, 0, 0], False, marks=pytest.mark.slow),
        ("lever_arm", [0, 0, 0, 4.0, -3.0, 2.0, 0, 0, 0], True),
    ],
)
def test_fits_equal_the_dense_weighted_least_squares(effect, theta, drop, monkeypatch):
    # the algebra on white rows (prewhitening is a row transform applied before it)
    from calib_core.discovery import noise

    monkeypatch.setattr(noise, "serial_noise", lambda z, real, t: noise.SerialNoise(np.zeros(6), np.ones(6)))
    sessions = _unit(11, effect, theta, drop=drop)
    d = _Discovery(sessions, 0.01)
    assert d.g.balanced is (not drop)
    L = _long(d)
    R = d.g.R
    subsets = [(), ("gyro_g_sensitivity",), ("lever_arm", "thermal_bias_drift")]
    for names in subsets:
        cols = d.g.cols(names)
        K, b, th, X, beta = _dense_fit(L, np.ones(len(L["y"]), bool), cols, R)
        f = d.fit(names)
        np.testing.assert_allclose(f.K, K, rtol=1e-9, atol=1e-12)
        np.testing.assert_allclose(d.biases(f), b, rtol=1e-7, atol=1e-10)
        np.testing.assert_allclose(f.theta, th, rtol=1e-7, atol=1e-9 * max(np.abs(th).max(initial=0), 1))
        z = (L["y"] - X @ beta) * L["w"]
        assert f.ss == pytest.approx(float(z @ z), rel=1e-9)
        ss_c = np.array([np.sum(z[L["channel"] == c] ** 2) for c in range(6)])
        np.testing.assert_allclose(f.ss_channel, ss_c, rtol=1e-9)
        # pure error: the two-way (step x repetition) residual per channel and test group
        pure = np.zeros(6)
        for c in range(6):
            for g in np.unique(L["group"]):
                m = (L["channel"] == c) & (L["group"] == g)
                e, _ = two_way_residual(z[m], L["step"][m], L["rep"][m])
                pure[c] += e @ e
        np.testing.assert_allclose(d.pure(names)[0], pure, rtol=1e-8)
        # held-out: each repetition predicted by the fit of the others, own biases refitted
        ss_h = np.zeros(6)
        for h in range(R):
            Kh, _, thh, Xh, betah = _dense_fit(L, L["rep"] != h, cols, R)
            rows = L["rep"] == h
            pred = np.einsum("ij,ij->i", L["raw"][rows], Kh[L["channel"][rows]]) + L["Z"][rows][:, cols] @ thh
            zh = (L["y"][rows] - pred) * L["w"][rows]
            for c in range(6):
                m = L["channel"][rows] == c
                w = L["w"][rows][m]
                e = zh[m] - w * (zh[m] @ w) / (w @ w)
                ss_h[c] += e @ e
        np.testing.assert_allclose(d.heldout_ss(names), ss_h, rtol=1e-8)


def test_noise_estimate_equals_the_replay_module():
    sessions = _unit(12, "gyro_scale_asymmetry", [0, 0, 600.0], n_reps=4, drop=True)
    d = _Discovery(sessions, 0.01)
    K, resid = d.noise_model(())
    white = d.g.white_sigma(K)
    real = d.g.real
    rep = np.broadcast_to(np.arange(d.g.R)[:, None, None], resid.shape)[real]
    step = np.broadcast_to(d.g.step[..., None], resid.shape)[real]
    grp = np.array(d.g.groups)[np.broadcast_to(d.g.gcode[..., None], resid.shape)[real]]
    ch = np.broadcast_to(np.array(CHANNELS), resid.shape)[real]
    expected = estimate_noise_arrays(ch, grp, rep, step, resid[real], white[real]).table
    rows = NoiseModel.from_residuals(d.g, K, resid).rows
    got = NoiseEstimate.from_records([dict(zip(expected.columns, r)) for r in rows], True).table
    assert list(got["channel"]) == list(expected["channel"])
    assert list(got["group"]) == list(expected["group"])
    assert list(got["dof"]) == list(expected["dof"])
    for col in ("step_sd", "white_sd", "instability_sd"):
        np.testing.assert_allclose(got[col], expected[col], rtol=1e-10)


def test_noise_estimate_records_and_table_agree():
    table = pd.DataFrame(
        {
            "channel": ["gx", "ax"],
            "group": ["rate", "position"],
            "dof": [8, 9],
            "step_sd": [0.1, 0.2],
            "white_sd": [0.05, 0.1],
            "instability_sd": [0.08, 0.17],
        }
    )
    a = NoiseEstimate(table, from_repetitions=True)
    assert a.records() == table.to_dict(orient="records")
    b = NoiseEstimate.from_records(a.records(), from_repetitions=False)
    pd.testing.assert_frame_equal(b.table, table)
    assert not b.from_repetitions
    with pytest.raises(ValueError):
        NoiseEstimate(None, True)


def test_stacked_theta_equals_one_problem_at_a_time():
    rng = np.random.default_rng(3)
    Z = rng.normal(size=(4, 12, 5))
    Z[1, :, 2] = 0.0  # a dead column
    Z[2, :, 4] = Z[2, :, 0] * 3.0  # a direction the data do not determine
    y = rng.normal(size=(4, 12))
    stacked = lstsq_pinv_stack(Z, y)
    for i in range(4):
        theta, _, _ = lstsq_pinv_cov(Z[i], y[i])
        np.testing.assert_allclose(stacked[i], theta, rtol=1e-12, atol=1e-14)


def test_undetermined_affine_model_is_a_design_error():
    """A channel whose raw output is constant within each repetition cannot determine its
    gain (the column is a copy of the bias): the same check as numpy's matrix_rank."""
    sessions = _unit(13, None, None)
    for sm in sessions:
        sm.gyro[:, 1] = 1.0 + sm.key.rep
    with pytest.raises(DesignError) as err:
        diagnose_unit(sessions, tables=False)
    # 3 repetitions: 3 gains + 3 biases, one raw column is a copy of the biases: rank 5
    assert err.value.code == "E_DISCOVERY_RANK" and "gx" in str(err.value)
    assert "rank 5 < 6" in str(err.value)


def test_same_motion_shares_design_columns_and_decisions_repeat():
    """The design columns of one protocol are computed once; a second diagnosis of the same
    unit (cache warm) gives exactly the same document."""
    sessions = _unit(14, "accel_scale_nonlinearity", [0.0, 0.8, 0.0])
    a = diagnose_unit(sessions, tables=False).to_dict()
    b = diagnose_unit(sessions, tables=False).to_dict()
    assert a == b
    assert [e["name"] for e in a["effects"]] == ["accel_scale_nonlinearity"]
