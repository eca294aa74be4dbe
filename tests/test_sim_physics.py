"""The physics simulator against first-principles expectations written here, independently
(explicit cross products and trigonometry, not the simulator's own helpers): sensing axes and
scales, lever arm at a 3-D position, Earth rate at a latitude, thermal coefficients, noise
densities, a tilted table axis, and that the xu2016 fit recovers the linear part."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from calib_core.models.xu2016 import fit_accel_multiposition, fit_gyro_multirate
from calib_core.sim.physics import (
    EARTH_RATE_DPS,
    Turntable,
    WarmUp,
    simulate_physics_session,
    typical_physics_unit,
)
from calib_core.sim.protocols import default_session, to_frame, xu2016_multirate
from schemas.physics_sessions import physics_unit_step_means

G = 9.80665


def _quiet(unit, temperature=None):
    q = lambda s: replace(s, white_density=0.0, instability=0.0, turn_on=0.0)  # noqa: E731
    return replace(
        unit, gyros=tuple(map(q, unit.gyros)), accels=tuple(map(q, unit.accels)), temperature=temperature
    )


def _ideal(unit):
    """Sensors exactly on the body axes, unit scale, no bias."""
    e = np.eye(3)
    return replace(
        unit,
        gyros=tuple(replace(s, axis=tuple(e[i]), scale=1.0, bias=0.0) for i, s in enumerate(unit.gyros)),
        accels=tuple(replace(s, axis=tuple(e[i]), scale=1.0, bias=0.0) for i, s in enumerate(unit.accels)),
    )


def _steps(pred):
    rows = [r for r in xu2016_multirate() if pred(r)]
    return to_frame(rows)


def _step_mean(samples, step, col, skip_s=0.5):
    s = samples[samples.step == step]
    s = s[s.t >= s.t.iloc[0] + skip_s]
    return float(s[col].astype(float).mean())


@pytest.fixture(scope="module")
def unit():
    return typical_physics_unit(np.random.default_rng(11))


def test_xu2016_fit_recovers_the_sensing_geometry(unit):
    """Raw = diag(scale) (axes . input) + scale * bias, so the paper's K is the inverse of the
    matrix whose rows are scale_i * axis_i, and w0 = -K (scale * bias)."""
    u = _quiet(unit)
    sm = physics_unit_step_means(u, default_session(), np.random.default_rng(0), n_reps=1)[0]
    for fit, sensors in ((fit_gyro_multirate(sm), u.gyros), (fit_accel_multiposition(sm), u.accels)):
        S = np.array([np.asarray(s.axis) * s.scale for s in sensors])
        K = np.linalg.inv(S)
        assert np.abs(fit.K - K).max() < 1e-6
        offset = fit.w0 if hasattr(fit, "w0") else fit.f0
        assert np.abs(offset + K @ np.array([s.scale * s.bias for s in sensors])).max() < 1e-5
    # the misalignment is what was asked for: 0.5 deg from the nominal axis
    for s in u.gyros + u.accels:
        ang = np.degrees(np.arccos(np.max(np.abs(s.axis))))
        assert ang == pytest.approx(0.5, abs=1e-9)


def test_lever_arm_is_centripetal_acceleration_at_the_full_position(unit):
    r = np.array([12.0, -6.0, 4.0])  # mm
    u = _ideal(_quiet(unit))
    u = replace(u, accels=tuple(replace(a, position_mm=tuple(r)) for a in u.accels))
    steps = _steps(lambda row: row["up_axis"] == "+x" and row["rate_dps"] in (300.0, -300.0))
    samples, _ = simulate_physics_session(u, steps, np.random.default_rng(0))
    w = np.radians(300.0)
    # rotation about body x: w x (w x r) = -w^2 (0, r_y, r_z); gravity +1 g on x
    expected = np.array([1.0, -(w**2) * r[1] * 1e-3 / G, -(w**2) * r[2] * 1e-3 / G])
    for step in steps.step:
        got = [_step_mean(samples, step, c) for c in ("ax", "ay", "az")]
        np.testing.assert_allclose(got, expected, atol=2e-6)


def test_misaligned_accelerometer_senses_the_leakage(unit):
    """An accelerometer tilted 0.5 deg towards x, at 10 mm along x, on a z rotation of
    3600 deg/s senses sin(0.5 deg) times the centripetal acceleration along x."""
    u = _ideal(_quiet(unit))
    tilt = np.radians(0.5)
    u = u.replace_accel(2, axis=(np.sin(tilt), 0.0, np.cos(tilt)), position_mm=(10.0, 0.0, 0.0))
    steps = _steps(lambda row: row["up_axis"] == "+z" and row["rate_dps"] == 3600.0)
    samples, _ = simulate_physics_session(u, steps, np.random.default_rng(0))
    w = np.radians(3600.0)
    expected = np.cos(tilt) * 1.0 + np.sin(tilt) * (-(w**2) * 10e-3 / G)
    assert _step_mean(samples, steps.step.iloc[0], "az") == pytest.approx(expected, abs=2e-5)


def test_earth_rate_at_latitude(unit):
    u = _ideal(_quiet(unit))
    lat = 45.0
    steps = _steps(lambda row: row["test"] == "stationary")
    samples, md = simulate_physics_session(
        u,
        steps,
        np.random.default_rng(0),
        table=Turntable(latitude_deg=lat, heading_deg=30.0, declare_location=True),
    )
    assert md["latitude_deg"] == "45" and md["table_heading_deg"] == "30"
    omega = 15.041067 / 3600.0  # deg/s
    for step, up in zip(steps.step, steps.up_axis):
        g = np.array([_step_mean(samples, step, c) for c in ("gx", "gy", "gz")])
        i = "xyz".index(up[1])
        assert g[i] == pytest.approx(omega * np.sin(np.radians(lat)), rel=1e-4)
        assert np.linalg.norm(g) == pytest.approx(omega, rel=1e-4)
    assert EARTH_RATE_DPS * 3600 == pytest.approx(15.041067, rel=1e-6)


def test_thermal_bias_and_scale_coefficients(unit):
    warm = WarmUp(start_c=25.0, rise_c=10.0, tau_s=600.0, noise_c=0.0)
    u = _ideal(_quiet(unit, temperature=warm))
    u = u.replace_gyro(2, bias_tc=0.01, scale_tc_ppm=300.0)
    steps = _steps(lambda row: row["up_axis"] == "+z")
    samples, _ = simulate_physics_session(u, steps, np.random.default_rng(0))
    for step, rate in zip(steps.step, steps.rate_dps):
        s = samples[(samples.step == step)]
        s = s[s.t >= s.t.iloc[0] + 0.5]
        dT = 10.0 * (1.0 - np.exp(-s.t.to_numpy() / 600.0))
        expected = np.mean(rate * (1.0 + 300e-6 * dT) + 0.01 * dT)
        assert float(s.gz.astype(float).mean()) == pytest.approx(expected, abs=1e-3)
        assert np.mean(s.temp_c) == pytest.approx(25.0 + np.mean(dT), abs=1e-3)


def test_white_noise_density_sets_the_per_sample_noise(unit):
    u = replace(_ideal(unit), temperature=None)
    u = replace(u, gyros=tuple(replace(g, instability=0.0, turn_on=0.0) for g in u.gyros))
    steps = _steps(lambda row: row["test"] == "stationary")
    steps["duration_s"] = 20.0
    for rate in (50.0, 200.0):
        samples, _ = simulate_physics_session(u, steps, np.random.default_rng(1), rate_hz=rate)
        sd = samples[samples.step >= 0].gx.astype(float).std()
        assert sd == pytest.approx(u.gyros[0].white_density * np.sqrt(rate), rel=0.05)


def test_table_rate_error_and_tilted_axis(unit):
    u = _ideal(_quiet(unit))
    steps = _steps(lambda row: row["up_axis"] == "+x" and row["rate_dps"] == 120.0)
    steps["duration_s"] = 3.5  # 0.5 s of settling, then 3 s = exactly one turn at 120 deg/s
    samples, _ = simulate_physics_session(
        u, steps, np.random.default_rng(0), table=Turntable(rate_scale_error=1e-3, axis_tilt_deg=2.0)
    )
    step = steps.step.iloc[0]
    assert _step_mean(samples, step, "gx") == pytest.approx(120.0 * 1.001, rel=1e-6)
    # gravity is 2 deg off the table axis (= body x): along it cos(2 deg); across it, it turns once
    # around during the kept turn (step mean ~0) with amplitude sin(2 deg)
    assert _step_mean(samples, step, "ax") == pytest.approx(np.cos(np.radians(2.0)), abs=1e-6)
    s = samples[samples.step == step]
    horiz = np.hypot(s.ay.astype(float), s.az.astype(float))
    assert horiz.max() == pytest.approx(np.sin(np.radians(2.0)), rel=1e-3)
