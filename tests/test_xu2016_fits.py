"""xu2016 estimators against known truth, and their standard errors against Monte Carlo."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from calib_core.errors import DesignError
from calib_core.models import xu2016
from calib_core.models.pipeline import calibrate_repetition
from calib_core.sim import protocols, simulator

STEPS = protocols.default_session(verification=True)


def _quiet(truth):
    return replace(
        truth,
        gyro_noise_dps=0.0,
        gyro_bias_instability_dps=0.0,
        accel_noise_g=0.0,
        accel_bias_instability_g=0.0,
    )


def test_noise_free_recovers_truth_exactly():
    rng = np.random.default_rng(11)
    truth = _quiet(simulator.typical_truth(rng, misalignment=0.02, scale=0.03))
    sm = simulator.simulate_step_means(truth, STEPS, rng)
    g = xu2016.fit_gyro_multirate(sm)
    a = xu2016.fit_accel_multiposition(sm)
    np.testing.assert_allclose(g.K, truth.K_g, atol=1e-12)
    np.testing.assert_allclose(g.w0, truth.w0, atol=1e-10)
    np.testing.assert_allclose(a.K, truth.K_a, atol=1e-12)
    np.testing.assert_allclose(a.f0, truth.f0, atol=1e-12)
    t = xu2016.fit_gyro_traditional(sm)
    K, w0 = t.as_affine()
    np.testing.assert_allclose(K, truth.K_g, atol=1e-10)
    np.testing.assert_allclose(w0, truth.w0, atol=1e-9)


def test_lsb_raw_units_are_absorbed_by_K():
    """Raw LSB: K_g carries deg/s per LSB, w0 stays in deg/s."""
    rng = np.random.default_rng(12)
    base = _quiet(simulator.typical_truth(rng))
    lsb = 0.07  # deg/s per LSB
    truth = replace(base, K_g=base.K_g * lsb, gyro_unit="LSB")
    sm = simulator.simulate_step_means(truth, STEPS, rng)
    g = xu2016.fit_gyro_multirate(sm)
    np.testing.assert_allclose(g.K, base.K_g * lsb, rtol=1e-10)
    np.testing.assert_allclose(g.w0, base.w0, atol=1e-9)
    assert g.parameters()[0].unit == "deg/s per LSB"


def test_kg_recovered_to_1e_minus_4_with_realistic_noise():
    rng = np.random.default_rng(13)
    truth = simulator.typical_truth(rng, gyro_noise_dps=0.1, gyro_bias_instability_dps=0.01)
    sm = simulator.simulate_step_means(truth, STEPS, rng)
    g = xu2016.fit_gyro_multirate(sm)
    assert np.abs(g.K - truth.K_g).max() < 1e-4
    assert np.abs(g.w0 - truth.w0).max() < 0.05


@pytest.mark.slow
def test_standard_errors_match_monte_carlo_spread():
    """(estimate - truth) / stderr over 200 sessions: mean ~ 0, std within 0.8-1.25."""
    rng = np.random.default_rng(2016)
    truth = simulator.typical_truth(rng, gyro_bias_repeatability_dps=0.02, accel_bias_repeatability_g=2e-4)
    z = {"gyro": [], "accel": [], "gyro_traditional": [], "accel_traditional": []}
    for _ in range(200):
        rep_truth = simulator.draw_repetition_truth(truth, rng)
        sm = simulator.simulate_step_means(rep_truth, STEPS, rng)
        g = xu2016.fit_gyro_multirate(sm)
        a = xu2016.fit_accel_multiposition(sm)
        z["gyro"].append(
            np.r_[((g.K - rep_truth.K_g) / g.K_stderr).ravel(), (g.w0 - rep_truth.w0) / g.w0_stderr]
        )
        z["accel"].append(
            np.r_[((a.K - rep_truth.K_a) / a.K_stderr).ravel(), (a.f0 - rep_truth.f0) / a.f0_stderr]
        )
        # traditional: true S = K^-1, b = -K^-1 x0
        for name, fit, K, x0 in (
            ("gyro_traditional", xu2016.fit_gyro_traditional(sm), rep_truth.K_g, rep_truth.w0),
            ("accel_traditional", xu2016.fit_accel_traditional(sm), rep_truth.K_a, rep_truth.f0),
        ):
            S = np.linalg.inv(K)
            z[name].append(np.r_[((fit.S - S) / fit.S_stderr).ravel(), (fit.b + S @ x0) / fit.b_stderr])
    for name, rows in z.items():
        zz = np.array(rows)
        assert np.all(np.abs(zz.mean(axis=0)) < 0.25), (name, zz.mean(axis=0))
        sd = zz.std(axis=0, ddof=1)
        assert np.all((sd > 0.8) & (sd < 1.25)), (name, sd)


def test_proposed_and_traditional_agree_within_noise_on_verification_sweep():
    """The paper's central claim (Table 3): same compensation, no inverse at run time."""
    rng = np.random.default_rng(3)
    truth = simulator.xu2016_truth(gyro_noise_dps=0.05, gyro_bias_instability_dps=0.005)
    sm = simulator.simulate_step_means(truth, STEPS, rng)
    g = xu2016.fit_gyro_multirate(sm)
    t = xu2016.fit_gyro_traditional(sm)
    ver = sm.of_test("verification")
    diff = g.compensate(ver.gyro) - t.compensate(ver.gyro)
    err = g.compensate(ver.gyro) - ver.w_ref
    # difference of the two compensations is far below the compensated error itself
    step_noise = g.step_sigma
    assert np.all(np.abs(diff) < 4 * step_noise * np.maximum(1, np.abs(ver.w_ref) / 300)), diff
    assert np.abs(err).max() < 1.0  # compensated within 1 deg/s up to 3600 deg/s
    uncomp = ver.gyro - ver.w_ref
    assert np.abs(uncomp).max() > 10 * np.abs(err).max()


def test_table3_layout():
    rng = np.random.default_rng(4)
    truth = simulator.xu2016_truth()
    sm = simulator.simulate_step_means(truth, STEPS, rng)
    fit = calibrate_repetition(sm)
    t3 = fit.compensation
    assert set(t3["method"]) == {"uncompensated", "proposed", "traditional"}
    assert set(t3["input_axis"]) == {"x", "y", "z"}
    assert len(t3) == 27 and (t3["err_min"] <= t3["err_max"]).all()
    # z input uncompensated z error follows the scale error 1.00579 -> ~ 0.58 % of 3600
    row = t3[(t3.input_axis == "z") & (t3.output_axis == "z") & (t3.method == "uncompensated")].iloc[0]
    assert 15 < max(-row.err_min, row.err_max) < 25


def test_no_rotation_about_one_axis_is_undetermined():
    rng = np.random.default_rng(5)
    truth = simulator.typical_truth(rng)
    steps = STEPS[~((STEPS["test"] == "multirate") & (STEPS["up_axis"] == "+z"))]
    sm = simulator.simulate_step_means(truth, steps, rng)
    with pytest.raises(DesignError) as exc:
        xu2016.fit_gyro_multirate(sm)
    assert exc.value.code == "E_UNDETERMINED"
    assert "z" in exc.value.reason and "gyro axis z" in exc.value.undetermined


def test_too_few_positions_is_undetermined():
    rng = np.random.default_rng(6)
    truth = simulator.typical_truth(rng)
    steps = STEPS[(STEPS["test"] != "multiposition") | (STEPS["angle_deg"] == 0)]
    sm = simulator.simulate_step_means(truth, steps, rng)
    with pytest.raises(DesignError, match="multiposition steps"):
        xu2016.fit_accel_multiposition(sm)


def test_missing_partner_step_drops_only_that_pair():
    rng = np.random.default_rng(7)
    truth = simulator.typical_truth(rng)
    sm = simulator.simulate_step_means(truth, STEPS, rng)
    full = xu2016.fit_gyro_multirate(sm)
    drop = sm.select(~((sm.test == "multirate") & (sm.rate_dps == -60) & (sm.up_axis == "+y")))
    part = xu2016.fit_gyro_multirate(drop)
    assert part.n_pairs == full.n_pairs - 1
    assert np.abs(part.K - full.K).max() < 5 * full.K_stderr.max()
