"""zhang2017 lever arms: the forward physics, recovery by the joint least squares, the paper's
closed form for contrast, undetermined components, compensation."""

import json

import numpy as np
import pytest

from calib_core.effects import MotionContext
from calib_core.errors import DesignError
from calib_core.models.zhang2017 import (
    compensate_specific_force,
    fit_accel_static,
    fit_lever_arm,
    paper_lever_arm,
)
from calib_core.sim import protocols
from calib_core.sim.accel_unit import AccelUnitTruth, SensitiveAxisLeverArm
from calib_core.sim.simulator import simulate_step_means

from conftest import PAPER_NOISE, paper_unit, random_unit

G = 9.80665


def test_centripetal_physics_by_hand():
    # x accelerometer exactly along x at r = (10, 0, 0) mm, rotating at 180 deg/s about z:
    # it senses the centripetal acceleration -w^2 r_x (towards the axis), in g
    u = AccelUnitTruth(
        scale=np.ones(3),
        bias=np.zeros(3),
        C=np.eye(3),
        lever_arm_mm=np.array([[10.0, 0, 0], [0, 0, 0], [0, 0, 0]]),
        unit="g",
    )
    w = np.pi  # rad/s
    out = u.raw([0.0, 0.0, 1.0], [0.0, 0.0, 180.0])[0]
    assert out[0] == pytest.approx(-(w**2) * 0.010 / G, rel=1e-12)
    assert out[1] == 0.0 and out[2] == pytest.approx(1.0)
    # angular acceleration about z of 90 deg/s^2: tangential dw/dt x r along +y, x unaffected
    u2 = AccelUnitTruth(
        scale=np.ones(3),
        bias=np.zeros(3),
        C=np.eye(3),
        lever_arm_mm=np.array([[0, 0, 0], [10.0, 0, 0], [0, 0, 0]]),
        unit="g",
    )
    out = u2.raw([0.0, 0.0, 0.0], [0.0, 0.0, 0.0], [0.0, 0.0, 90.0])[0]
    assert out[1] == pytest.approx(np.pi / 2 * 0.010 / G, rel=1e-12)


def test_simulator_effect_equals_unit_forward_model():
    u = paper_unit()
    mimu = u.to_mimu_truth()
    rng = np.random.default_rng(0)
    f, w, dw = rng.normal(size=(20, 3)), rng.normal(0, 200, (20, 3)), rng.normal(0, 50, (20, 3))
    _, A = mimu.raw_outputs(MotionContext.from_refs(w, f, dwdt=dw))
    assert np.max(np.abs(A - u.raw(f, w, dw))) < 1e-13
    assert SensitiveAxisLeverArm(u.C).regressors(MotionContext.from_refs(w, f)).shape == (20, 6, 9)


def _fits(u, steps, seed, **noise):
    sm = simulate_step_means(u.to_mimu_truth(**(noise or PAPER_NOISE)), steps, np.random.default_rng(seed))
    st = fit_accel_static(sm)
    return sm, st, fit_lever_arm(sm, st)


@pytest.mark.parametrize("seed", range(6))
def test_lever_arm_recovered_within_0p2_mm(seed):
    rng = np.random.default_rng(100 + seed)
    u = paper_unit() if seed == 0 else random_unit(rng, tilt_deg=2.0)
    sm, st, lv = _fits(u, protocols.zhang2017_session(), seed)
    assert lv.model == "lever_arm" and lv.undetermined == ()
    assert np.max(np.abs(lv.lever_arm_mm - u.lever_arm_mm)) < 0.2
    assert np.max(np.abs(st.angles_deg - u.angles_deg)) < 0.01
    assert lv.condition_number < 10
    d = lv.to_dict()
    json.dumps(d)
    assert np.array(d["lever_arm_mm"]).shape == (3, 3) and np.array(d["stderr"]).shape == (3, 3)
    assert [p.name for p in lv.parameters()][:3] == ["r1x", "r1y", "r1z"]


def test_rates_from_calibrated_gyros():
    u = paper_unit()
    K_g = np.array([[1.01, 0.01, -0.005], [-0.02, 0.99, 0.01], [0.004, 0.012, 1.002]])
    w0 = np.array([0.3, -0.2, 0.5])
    mimu = u.to_mimu_truth(K_g=K_g, w0=w0, gyro_noise_dps=0.01, **PAPER_NOISE)
    sm = simulate_step_means(mimu, protocols.zhang2017_session(), np.random.default_rng(4))
    st = fit_accel_static(sm)
    lv = fit_lever_arm(sm, st, gyro_K=K_g, gyro_w0=w0)
    assert lv.rate_source == "gyro"
    assert np.max(np.abs(lv.lever_arm_mm - u.lever_arm_mm)) < 0.2
    # with uncalibrated gyro outputs taken as rates (K = I, w0 = 0) the 1-2 % scale errors
    # bias r by the same fraction of 8 mm: visibly worse
    bad = fit_lever_arm(sm, st, gyro_K=np.eye(3), gyro_w0=np.zeros(3))
    assert np.max(np.abs(bad.lever_arm_mm - u.lever_arm_mm)) > 0.2


def test_axis_only_steps_report_off_diagonals_undetermined():
    u = paper_unit()
    steps = protocols.zhang2017_session(tilted=False)
    sm, st, lv = _fits(u, steps, 11)
    off = [f"r{i + 1}{a}" for i in range(3) for j, a in enumerate("xyz") if i != j]
    assert sorted(lv.undetermined) == sorted(off)
    assert all("tilted" in lv.reasons[n] for n in off)
    assert np.isnan(lv.lever_arm_mm[~np.eye(3, dtype=bool)]).all()
    assert np.isnan(lv.stderr[~np.eye(3, dtype=bool)]).all()
    # the diagonal is still estimated; fixing the off-diagonals at 0 biases it by about
    # cos(theta_ik) r_ik (~0.03 mm here)
    assert np.max(np.abs(np.diag(lv.lever_arm_mm) - np.diag(u.lever_arm_mm))) < 0.1
    d = lv.to_dict()
    assert d["lever_arm_mm"][0][1] is None and "r1y" in d["undetermined"]
    assert np.isfinite(lv.condition_number) and lv.condition_number_full > 50


@pytest.mark.parametrize("dynamic", [[7, 8], [7, 14]])
def test_fewer_dynamic_steps_than_components_report_the_rest_undetermined(dynamic):
    """Two dynamic steps give each block's QR two pivots for three components: the third is
    undetermined with its reason (it used to be an IndexError, i.e. E_INTERNAL)."""
    steps = protocols.zhang2017_session(tilted=False)
    steps = steps[(steps.test != "dynamic") | steps.step.isin(dynamic)]
    sm, st, lv = _fits(paper_unit(), steps, 3)
    assert len(lv.undetermined) >= 3  # at least one component per block
    assert all("not observable" in lv.reasons[n] for n in lv.undetermined)
    names = [f"r{i + 1}{a}" for i in range(3) for a in "xyz"]
    undetermined = np.array([n in lv.undetermined for n in names]).reshape(3, 3)
    assert np.isnan(lv.lever_arm_mm[undetermined]).all()
    assert np.isfinite(lv.lever_arm_mm[~undetermined]).all()


def test_no_dynamic_steps_is_a_design_error():
    u = paper_unit()
    steps = protocols.to_frame(protocols.zhang2017_six_position())
    sm = simulate_step_means(u.to_mimu_truth(**PAPER_NOISE), steps, np.random.default_rng(0))
    with pytest.raises(DesignError) as e:
        fit_lever_arm(sm, fit_accel_static(sm))
    assert e.value.code == "E_NO_DYNAMIC_STEPS"


def test_paper_formula_blows_up_joint_ls_does_not():
    # a well-aligned unit: the cosines the paper divides by are ~3e-5 (0.002 deg)
    c = np.eye(3) + np.array([[0, 3e-5, -2e-5], [-4e-5, 0, 2.5e-5], [3e-5, -3e-5, 0]])
    c /= np.linalg.norm(c, axis=1, keepdims=True)
    r = np.array([[-8.0, 1.0, -1.5], [0.8, -8.0, 0.6], [-1.2, 0.5, -8.0]])
    u = AccelUnitTruth(
        scale=np.array([0.40, 0.41, 0.39]), bias=np.array([2.4, 2.5, 2.45]), C=c.T, lever_arm_mm=r
    )
    sm, st, lv = _fits(u, protocols.zhang2017_session(), 5)
    paper = paper_lever_arm(sm, st)
    off = ~np.eye(3, dtype=bool)
    assert np.max(np.abs(paper[off] - r[off])) > 10.0  # tens of mm or more: "distortion"
    # on the diagonal (cosines ~1) the formula is fine
    assert np.max(np.abs(np.diag(paper) - np.diag(r))) < 0.2
    assert np.max(np.abs(lv.lever_arm_mm - r)) < 0.2
    assert lv.undetermined == ()


def test_paper_formula_agrees_when_noise_free():
    # sanity of the closed form itself: exact on noise-free data for a misaligned unit
    u = random_unit(np.random.default_rng(3), tilt_deg=3.0)
    noise = dict(accel_noise_g=0.0, accel_bias_instability_g=0.0)
    sm, st, lv = _fits(u, protocols.zhang2017_session(), 0, **noise)
    assert np.max(np.abs(paper_lever_arm(sm, st) - u.lever_arm_mm)) < 1e-6
    assert np.max(np.abs(lv.lever_arm_mm - u.lever_arm_mm)) < 1e-6


def test_compensation_inverts_the_forward_model():
    u = random_unit(np.random.default_rng(8), tilt_deg=3.0)
    sm, st, lv = _fits(u, protocols.zhang2017_session(), 1, accel_noise_g=0.0, accel_bias_instability_g=0.0)
    rng = np.random.default_rng(9)
    f = rng.normal(size=(50, 3))
    w = rng.normal(0, 300, (50, 3))
    dw = rng.normal(0, 200, (50, 3))
    A = u.raw(f, w, dw)
    assert np.max(np.abs(compensate_specific_force(st, lv, A, w, dw) - f)) < 1e-9
    # static only leaves the lever-arm term: ~ w^2 r = (5.2 rad/s)^2 * 8 mm ~ 22 mg
    err_static = np.max(np.abs(compensate_specific_force(st, None, A) - f))
    assert err_static > 5e-3


def _catalogue_truth(noise: bool):
    """xu2016's unit with its accelerometers on the body axes, with the catalogue's lever_arm
    term."""
    from dataclasses import replace

    from calib_core.effects import get_effect
    from calib_core.sim import simulator

    r = np.array([[8.0, 0.5, -0.3], [0.2, 8.0, 0.1], [-0.4, 0.3, 8.0]])
    # accelerometers on the body axes (xu2016's scales, no misalignment): the catalogue's
    # lever arm, which acts along each sensing direction, is then the body-axis model
    t = simulator.xu2016_truth()
    t = replace(t, K_a=np.diag(np.diag(t.K_a)))
    if not noise:
        t = replace(t, accel_noise_g=0.0, accel_bias_instability_g=0.0)
    return t.with_effects((get_effect("lever_arm"), r.ravel())), r


def test_body_axis_stderr_matches_monte_carlo():
    t, r = _catalogue_truth(noise=True)
    steps = protocols.default_session()
    rng = np.random.default_rng(77)
    z = []
    for _ in range(200):
        sm = simulate_step_means(t, steps, rng)
        lv = fit_lever_arm(sm, fit_accel_static(sm), projection="body_axis")
        z.append(((lv.lever_arm_mm - r) / lv.stderr).ravel())
    sd = np.std(z, axis=0, ddof=1)
    assert np.all((sd > 0.8) & (sd < 1.25)), sd
    assert np.all(np.abs(np.mean(z, axis=0)) < 0.3)
