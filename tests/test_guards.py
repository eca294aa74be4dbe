"""Absurd estimates are refused with E_IMPLAUSIBLE, plausible ones pass (issue 8 item 6)."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from calib_core.errors import DesignError
from calib_core.guards import check_affine
from calib_core.models.pipeline import calibrate_repetition
from calib_core.sim import protocols, simulator

STEPS = protocols.default_session()


def test_typical_units_pass():
    rng = np.random.default_rng(1)
    for _ in range(20):
        sm = simulator.simulate_step_means(simulator.typical_truth(rng), STEPS, rng)
        calibrate_repetition(sm)  # no exception


def test_rate_table_in_wrong_unit_is_refused():
    """Raw deg/s that are really rad/s-scaled give K_g ~ 57: not a sensor, refused."""
    rng = np.random.default_rng(2)
    base = simulator.typical_truth(rng)
    truth = replace(base, K_g=base.K_g * 180 / np.pi, gyro_range_dps=(1e5, 1e5, 1e5))
    sm = simulator.simulate_step_means(truth, STEPS, rng)
    with pytest.raises(DesignError) as exc:
        calibrate_repetition(sm)
    assert exc.value.code == "E_IMPLAUSIBLE"
    assert "k_g11" in exc.value.reason and "[0.75, 1.25]" in exc.value.reason


def test_raw_lsb_scale_is_not_judged_but_bias_beyond_full_scale_is():
    K = np.eye(3) * 0.07
    assert check_affine("gyro", "k_g", K, np.zeros(3), "LSB", np.full(3, 300.0)) == []
    bad = check_affine("gyro", "k_g", K, np.array([0.0, 500.0, 0.0]), "LSB", np.full(3, 300.0))
    assert [b.parameter for b in bad] == ["w0_y"]
    nan = check_affine("accel", "k_a", np.full((3, 3), np.nan), np.zeros(3), "g", np.full(3, 8.0))
    assert nan and nan[0].limit == "finite values"


def test_stacked_precheck_clears_only_what_check_affine_passes():
    """guards.surely_plausible (the stacked pre-check of a unit's repetitions) never clears
    a session check_affine would refuse, and clears the plausible ones: K and biases on and
    around every limit, NaN and infinite values, a NaN full scale, both raw units."""
    from calib_core.guards import CROSS_AXIS_LIMIT, SCALE_LIMITS, surely_plausible

    rng = np.random.default_rng(11)
    R = 400
    K = np.eye(3) + rng.normal(scale=0.05, size=(R, 3, 3))
    x0 = rng.normal(scale=50.0, size=(R, 3))
    full_scale = np.tile([300.0, 300.0, 3600.0], (R, 1))
    for r in range(0, R, 7):  # values on the limits and just beyond them
        i, j = rng.integers(3, size=2)
        K[r, i, i] = rng.choice([SCALE_LIMITS[0], SCALE_LIMITS[1], 0.7499, 1.2501])
        if i != j:
            K[r, i, j] = rng.choice([CROSS_AXIS_LIMIT, -CROSS_AXIS_LIMIT, 0.2001, -0.2001])
        x0[r, j] = rng.choice([-1.0, 1.0]) * full_scale[r, j] * rng.choice([1.0, 1.0001])
    K[3, 1, 2], x0[10, 0], K[17, 0, 0], x0[24, 2] = np.nan, np.inf, -np.inf, np.nan
    full_scale[31, 1] = np.nan
    for raw_unit in ("deg/s", "LSB"):
        clear = surely_plausible("gyro", K, x0, raw_unit, full_scale)
        found = [check_affine("gyro", "k_g", K[r], x0[r], raw_unit, full_scale[r]) for r in range(R)]
        assert not any(c and f for c, f in zip(clear, found))  # nothing refused is cleared
        passed = np.array([not f for f in found]) & np.isfinite(full_scale).all(axis=1)
        assert np.array_equal(clear, passed)  # and everything else check_affine passes is
        assert np.count_nonzero(~clear) >= 20 and np.count_nonzero(clear) >= R // 2  # both kinds occur
