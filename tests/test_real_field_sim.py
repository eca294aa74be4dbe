"""The field (Tedaldi 2014) estimator against known truth on a simulated hand-moved session,
and the static detector against the known rest intervals of that simulation."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from calib_core.models.field.imu_tk import field_calibration, misalignment
from calib_core.models.field.static_detection import detect_static, moving_variance_magnitude

G_LOCAL = 9.81
RATE = 100.0


def simulate_hand_session(
    rng, n_poses=18, init_s=8.0, rest_s=3.0, move_s=1.2, acc_noise=3.0, gyro_noise=8.0, gyro_g_dps=None
):
    """Raw counts of an IMU moved by hand: rest, then ``n_poses`` rotations about random
    body-fixed axes (raised-cosine angle profile, 60..150 deg), each followed by a rest.
    ``gyro_g_dps`` (3x3, deg/s per g) adds a gyro g-sensitivity. Returns t, raw gyro, raw
    accel, truth dict, true rest mask."""
    truth = {
        "acc_mis": rng.normal(0, 0.01, 3),  # a_yz, a_zy, a_zx
        "acc_scale": (9.81 / 420) * (1 + rng.normal(0, 0.01, 3)),  # m/s^2 per count
        "acc_bias": 32768 + rng.normal(0, 300, 3),
        "gyro_mis": rng.normal(0, 0.01, 6),
        "gyro_scale": (1 / 5000) * (1 + rng.normal(0, 0.02, 3)),  # rad/s per count
        "gyro_bias": 32768 + rng.normal(0, 300, 3),
    }
    n_rest0 = int(init_s * RATE)
    n_rest = int(rest_s * RATE)
    n_move = int(move_s * RATE)
    R = Rotation.from_rotvec(rng.normal(0, 1, 3))
    w_list, R_list, rest = [], [], []

    def hold(n):
        w_list.append(np.zeros((n, 3)))
        R_list.extend([R] * n)
        rest.append(np.ones(n, bool))

    hold(n_rest0)
    for _ in range(n_poses):
        axis = rng.normal(0, 1, 3)
        axis /= np.linalg.norm(axis)
        total = np.radians(rng.uniform(60, 150)) * rng.choice([-1, 1])
        tau = np.arange(n_move) / RATE
        # angle(t) = total (1 - cos(pi t / T)) / 2 sampled at t_k; rate is its derivative
        rate = total * np.pi / (2 * move_s) * np.sin(np.pi * tau / move_s)
        angle = total * (1 - np.cos(np.pi * tau / move_s)) / 2
        R0 = R
        for k in range(n_move):
            R_list.append(R0 * Rotation.from_rotvec(axis * angle[k]))
        w_list.append(rate[:, None] * axis)
        rest.append(np.zeros(n_move, bool))
        R = R0 * Rotation.from_rotvec(axis * total)
        hold(n_rest)
    w = np.vstack(w_list)
    rest = np.concatenate(rest)
    quats = np.array([r.as_quat() for r in R_list])
    f = Rotation.from_quat(quats).inv().apply([0.0, 0.0, G_LOCAL])  # specific force, body
    Ma = misalignment(*truth["acc_mis"]) @ np.diag(truth["acc_scale"])
    Mg = misalignment(*truth["gyro_mis"]) @ np.diag(truth["gyro_scale"])
    A = np.linalg.solve(Ma, f.T).T + truth["acc_bias"] + rng.normal(0, acc_noise, f.shape)
    if gyro_g_dps is not None:
        w = w + np.radians(f / G_LOCAL @ np.asarray(gyro_g_dps).T)
    G = np.linalg.solve(Mg, w.T).T + truth["gyro_bias"] + rng.normal(0, gyro_noise, w.shape)
    t = np.arange(len(w)) / RATE
    return t, G, A, truth, rest


@pytest.fixture(scope="module")
def sim():
    rng = np.random.default_rng(20260521)
    t, G, A, truth, rest = simulate_hand_session(rng)
    res = field_calibration(t, G, A, G_LOCAL, init_static_s=8.0, min_intervals=12)
    return t, G, A, truth, rest, res


def test_field_recovers_accel_truth(sim):
    t, G, A, truth, rest, res = sim
    p = res.accel.params
    # Tolerances ~4x the RMS error measured by Monte Carlo over 30 simulated sessions (seeds
    # 100..129, same settings): misalignment 1.0-1.3e-3 rad, scale 0.6-0.7e-3 (relative),
    # bias 0.24-0.27 counts. Noise-free sessions give errors < 1e-5 (no estimator bias).
    np.testing.assert_allclose(p[0:3], truth["acc_mis"], atol=5e-3)
    np.testing.assert_allclose(p[3:6] / truth["acc_scale"], 1, atol=3e-3)
    np.testing.assert_allclose(p[6:9], truth["acc_bias"], atol=1.1)
    # the Calibration form maps raw -> g exactly as the truth does
    Ma = misalignment(*truth["acc_mis"]) @ np.diag(truth["acc_scale"])
    np.testing.assert_allclose(
        res.calibration.K_a, Ma / G_LOCAL, rtol=0, atol=5e-3 * np.abs(Ma / G_LOCAL).max()
    )


def test_field_recovers_gyro_truth(sim):
    t, G, A, truth, rest, res = sim
    p = res.gyro.params
    # Monte Carlo RMS errors (30 sessions): misalignment 0.5-0.95e-3 rad, scale 0.4-0.56e-3,
    # bias 0.25-0.28 counts (= 8 counts / sqrt(800 rest samples)), largest transition angle
    # 0.2 deg; tolerances ~4x those.
    np.testing.assert_allclose(p[:6], truth["gyro_mis"], atol=4e-3)
    np.testing.assert_allclose(p[6:9] / truth["gyro_scale"], 1, atol=2.5e-3)
    np.testing.assert_allclose(res.gyro.bias, truth["gyro_bias"], atol=1.1)
    assert res.stats["gyro_angle_max_deg"] < 0.8


def test_detector_finds_the_rest_periods(sim):
    t, G, A, truth, rest, res = sim
    det = res.accel.detection
    # every detected static sample is truly at rest (no motion sample labelled static)
    assert not (det.mask & ~rest).any()
    # one detected interval per rest period (initial + 18 poses), each inside a rest run
    assert len(det.intervals) == 19
    # and the quantile floor (no initial period given) finds the same number of poses
    q = detect_static(A, multiplier=res.accel.multiplier, quantile=0.05)
    assert len(q.intervals) == 19 and not (q.mask & ~rest).any()


def test_moving_variance_matches_direct_computation():
    rng = np.random.default_rng(7)
    x = rng.normal(0, 1, (500, 3)) * [1, 2, 3] + 32768
    s = moving_variance_magnitude(x, 51)
    i = 200
    direct = np.linalg.norm(np.var(x[i - 25 : i + 26], axis=0, ddof=1))
    assert s[i] == pytest.approx(direct, rel=1e-9)
    assert np.isnan(s[:25]).all() and np.isnan(s[-25:]).all() and np.isfinite(s[25:-25]).all()


def test_field_recovers_gyro_g_sensitivity():
    """Injected g-sensitivity (deg/s per g) is recovered from the static poses. Tolerance:
    pose-mean gyro noise 8 counts / sqrt(~250) = 0.5 count = 0.006 deg/s over 19 poses
    spanning +/-1 g; measured max error 0.003-0.005 deg/s per g over 5 seeds; 0.015 = 3x."""
    rng = np.random.default_rng(99)
    S = rng.normal(0, 0.1, (3, 3))
    t, G, A, truth, rest = simulate_hand_session(rng, gyro_g_dps=S)
    res = field_calibration(t, G, A, G_LOCAL, init_static_s=8.0, gyro_g_sensitivity=True, multipliers=[4])
    (term,) = res.calibration.terms
    assert term.name == "gyro_g_sensitivity"
    np.testing.assert_allclose(term.params.reshape(3, 3), S, atol=0.015)
    np.testing.assert_allclose(res.gyro.params[6:9] / truth["gyro_scale"], 1, atol=2.5e-3)
    assert res.stats["gyro_static_rate_rms_dps"] < 0.02
