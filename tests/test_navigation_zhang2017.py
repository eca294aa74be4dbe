"""Strapdown navigation of a turntable trajectory with a lever-armed unit: integration accuracy
and the navigation benefit of the lever-arm compensation."""

import numpy as np
import pytest

from calib_core.models.zhang2017 import fit_accel_static, fit_lever_arm
from calib_core.sim import protocols
from calib_core.sim.accel_unit import AccelUnitTruth
from calib_core.sim.navigation import (
    TurntableTrajectory,
    integrate_attitude,
    integrate_navigation,
    simulate_navigation,
)
from calib_core.sim.simulator import simulate_step_means

from conftest import PAPER_NOISE, random_unit


def test_trajectory_is_a_rotation_about_the_vertical():
    tr = TurntableTrajectory(axis_body=(1, 2, 2), rate_dps=90.0, rate_amplitude_dps=30.0, duration_s=10.0)
    m = tr.motion()
    u = np.array([1, 2, 2]) / 3.0
    # the body axis stays vertical, gravity (+1 g specific force) stays along it
    assert np.allclose(np.einsum("nij,j->ni", m["C_nb"], u), [0, 0, 1], atol=1e-12)
    assert np.allclose(m["f"], u, atol=1e-12)
    # rate and its derivative are consistent
    assert np.allclose(np.gradient(m["w"], 0.01, axis=0)[1:-1], m["dwdt"][1:-1], atol=0.05)
    # the gyro-integrated attitude matches the true one: the trapezoidal increment errs by
    # rate'' dt^3 / 12 per step (3 deg/s^3 here): ~4e-6 rad after 10 s
    C = integrate_attitude(m["C_nb"][0], m["w"], 0.01)
    assert np.max(np.abs(C - m["C_nb"])) < 1e-5
    # exact for a constant rate
    m = TurntableTrajectory(axis_body=(1, 2, 2), rate_dps=150.0, duration_s=10.0).motion()
    C = integrate_attitude(m["C_nb"][0], m["w"], 0.01)
    assert np.max(np.abs(C - m["C_nb"])) < 1e-11


def test_ideal_unit_navigates_without_error():
    # a perfect specific force gives zero velocity; a 1 mg constant vertical error gives the
    # textbook v = a t, p = a t^2 / 2
    tr = TurntableTrajectory(duration_s=100.0)
    m = tr.motion()
    v, p = integrate_navigation(m["C_nb"], m["f"], 0.01, 9.80665)
    assert np.max(np.abs(v)) < 1e-9 and np.max(np.abs(p)) < 1e-7
    v, p = integrate_navigation(m["C_nb"], m["f"] * 1.001, 0.01, 9.80665)
    assert v[-1, 2] == pytest.approx(1e-3 * 9.80665 * 100.0, rel=1e-9)
    assert p[-1, 2] == pytest.approx(0.5e-3 * 9.80665 * 100.0**2, rel=1e-6)


@pytest.mark.parametrize(
    "traj",
    [
        TurntableTrajectory(axis_body=(1, 1, 1), rate_dps=100.0),
        TurntableTrajectory(
            axis_body=(1, 0.5, 1), rate_dps=100.0, rate_amplitude_dps=50.0, rate_period_s=15.0
        ),
    ],
    ids=["constant-100dps", "varying-100+-50dps"],
)
def test_lever_arm_compensation_10x_better_than_static_only(traj):
    rng = np.random.default_rng(21)
    base = random_unit(rng, tilt_deg=1.0)
    r8 = np.array([[8.0, 0.5, -0.4], [-0.6, 8.0, 0.3], [0.2, -0.5, 8.0]])  # 8 mm lever arms
    truth = AccelUnitTruth(scale=base.scale, bias=base.bias, C=base.C, lever_arm_mm=r8)
    sm = simulate_step_means(
        truth.to_mimu_truth(**PAPER_NOISE), protocols.zhang2017_session(), np.random.default_rng(22)
    )
    st = fit_accel_static(sm)
    lv = fit_lever_arm(sm, st)
    res = simulate_navigation(truth, st, lv, traj, np.random.default_rng(23))
    fin = res.final()
    assert set(fin) == {"none", "static", "static+dynamic"}
    assert res.velocity_error["static"].shape == (len(res.t), 3)
    assert res.t[-1] == pytest.approx(100.0)
    # the size effect (2/3 w^2 r ~ 1.6 cm/s^2 along the axis) makes static-only drift by m/s
    assert fin["static"]["velocity_mps"] > 1.0
    assert fin["static+dynamic"]["velocity_mps"] * 10 < fin["static"]["velocity_mps"]
    assert fin["static+dynamic"]["position_m"] * 10 < fin["static"]["position_m"]
    # and the same holds over the whole run, not only at its last sample
    v_s = np.linalg.norm(res.velocity_error["static"][-1000:], axis=1).mean()
    v_d = np.linalg.norm(res.velocity_error["static+dynamic"][-1000:], axis=1).mean()
    assert v_d * 10 < v_s


def test_navigation_impact_replays_the_fitted_unit():
    from calib_core.paper.zhang2017 import paper_truth
    from calib_core.sim.navigation import navigation_impact

    t = paper_truth()
    sm = simulate_step_means(
        t.to_mimu_truth(**PAPER_NOISE), protocols.zhang2017_session(), np.random.default_rng(0)
    )
    st = fit_accel_static(sm)
    fin = navigation_impact(st, fit_lever_arm(sm, st)).final()
    # by hand from Table 3 about u = (1,1,1)/sqrt(3): accelerometer i senses
    # w^2 (u_i (u . r_i) - r_ii) = w^2 x (4.98, 5.01, 5.13) mm, i.e. sqrt(3) w^2 5.04 mm =
    # 2.66 cm/s^2 along the (vertical) axis -> 2.66 m/s after 100 s
    expected = np.sqrt(3) * np.radians(100.0) ** 2 * 5.04e-3 * 100.0
    assert abs(fin["static"]["velocity_mps"] - expected) < 0.1
    assert fin["static+dynamic"]["velocity_mps"] < 1e-6  # own model as truth, no noise


def _sequential_attitude(C0, w_dps, dt):
    """Reference: the step-by-step rotation-vector update (one Rodrigues rotation matrix per
    step, composed in order), independent of the quaternion code under test."""
    out = [C0]
    C = C0.copy()
    for a in 0.5 * (w_dps[1:] + w_dps[:-1]) * np.radians(dt):
        ang = np.linalg.norm(a)
        K = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
        if ang > 0:
            K = K / ang
        C = C @ (np.eye(3) + np.sin(ang) * K + (1 - np.cos(ang)) * K @ K)
        out.append(C)
    return np.array(out)


@pytest.mark.parametrize("n", [1, 2, 3, 1000, 1025])
def test_attitude_scan_equals_the_step_by_step_update(n):
    # a tumbling rate (axis not fixed), so the order of the rotations matters
    rng = np.random.default_rng(n)
    t = np.arange(n) * 0.01
    w = np.column_stack([200 * np.sin(0.7 * t), 150 * np.cos(1.3 * t), 80 + 20 * t])
    w = w + rng.normal(0, 5, w.shape)
    C0 = np.linalg.qr(rng.normal(size=(3, 3)))[0]
    C0 = C0 * np.sign(np.linalg.det(C0))
    C = integrate_attitude(C0, w, 0.01)
    assert C.shape == (n, 3, 3)
    assert np.max(np.abs(C - _sequential_attitude(C0, w, 0.01))) < 1e-11
    # orthonormal throughout
    assert np.max(np.abs(np.einsum("nij,nkj->nik", C, C) - np.eye(3))) < 1e-12
