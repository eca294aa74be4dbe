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
