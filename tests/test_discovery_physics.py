"""Model discovery on the independent physics simulator (:mod:`calib_core.sim.physics`):
sensors misaligned by about 0.5 deg, realistic noise with a wandering bias, warm-up ramp.
Seeded small samples of the figures in docs/model-discovery.md
(``docs/model_discovery_figures.py physics``)."""
from __future__ import annotations

import json

import numpy as np
import pytest

from calib_core import protocols
from calib_core.discovery import diagnose_unit
from calib_core.discovery.evaluation import run_scenario
from calib_core.effects import (EffectTerm, FigureVariable, catalogue, get_effect,
                                register_effect, unregister_effect)
from calib_core.sim.physics import typical_physics_unit
from schemas.calibration_file import calibration_from_dict, calibration_to_dict
from schemas.physics_sessions import physics_unit_step_means

STEPS = protocols.default_session()


def step_means_of(unit, steps, rng, unit_id):
    return physics_unit_step_means(unit, steps, rng, n_reps=5, unit_id=unit_id)


@pytest.mark.slow
def test_clean_units_get_no_named_effect():
    t = run_scenario(step_means_of, STEPS, 16, seed=401)
    assert t.any_named == 0, t.misses


@pytest.mark.slow
@pytest.mark.parametrize("name", ["accel_scale_nonlinearity", "gyro_g_sensitivity",
                                  "gyro_scale_asymmetry", "gyro_scale_nonlinearity"])
def test_hidden_effect_is_named_alone(name):
    t = run_scenario(step_means_of, STEPS, 6, seed=500 + len(name), hidden=(name,))
    assert t.extra == 0, t.misses
    assert t.exact >= 5, t.misses


@pytest.mark.slow
def test_error_outside_the_catalogue_is_unexplained_never_named():
    t = run_scenario(step_means_of, STEPS, 5, seed=130, out_of_catalogue="periodic_rate_error")
    assert t.any_named == 0, t.misses
    assert t.misfit == t.unexplained == 5


@register_effect
class _PeriodicRateError(EffectTerm):
    """A term registered by this test only: error periodic in the gyro's own input."""

    name = "test_periodic_rate_error"
    description = "periodic rate error, period 130 deg/s"
    param_names = ("s_x", "s_y", "s_z")
    param_units = ("deg/s",) * 3
    excited_by = "rotation steps over the rate range"
    max_useful_stderr = 1.0

    def sensor_regressors(self, ctx, geometry):
        u = geometry.sensor_inputs(ctx)[0]
        out = np.zeros((len(ctx), 6, 3))
        for i in range(3):
            out[:, i, i] = np.sin(2 * np.pi * u[:, i] / 130.0)
        return out

    def realistic(self, rng, scale=1.0):
        theta = np.zeros(3)
        i = int(rng.integers(3))
        theta[i] = rng.choice([-1.0, 1.0]) * rng.uniform(0.03, 0.08) * scale
        return theta, f"gyro {'xyz'[i]}"

    def physics_knobs(self, theta):
        return {("gyro", i): {"periodic_amp": float(theta[i]), "periodic_period_dps": 130.0}
                for i in range(3) if theta[i]}

    def figure_variable(self, ctx, channel):
        return FigureVariable("rate on the gyro's own axis", "deg/s", ctx.w[:, channel % 3])


unregister_effect(_PeriodicRateError.name)  # registered only inside the test below


@pytest.mark.slow
def test_a_new_catalogue_module_is_all_it_takes():
    """One class with its registration: the periodic error it models is then named."""
    register_effect(_PeriodicRateError)
    try:
        t = run_scenario(step_means_of, STEPS, 4, seed=131, hidden=(_PeriodicRateError.name,))
    finally:
        unregister_effect(_PeriodicRateError.name)
    assert _PeriodicRateError.name not in catalogue()
    assert t.exact >= 3, t.misses


def test_undetermined_lever_arm_components_are_null_in_every_file():
    """Without the tilted dynamic steps the components of a lever arm along the rotation
    axes are not excited: they are undetermined, written as null with their reason, the
    documents are strict JSON and the calibration file reads back."""
    rng = np.random.default_rng(17)
    steps = protocols.default_session(dynamic=False)
    unit, theta, _ = get_effect("lever_arm").hide(typical_physics_unit(rng), rng)
    d = diagnose_unit(step_means_of(unit, steps, rng, "L1"), tables=False)
    doc = json.loads(json.dumps(d.to_dict(), allow_nan=False))
    (lever,) = [e for e in doc["effects"] + doc["partial"] if e["name"] == "lever_arm"]
    assert lever["undetermined"], lever
    for p in lever["undetermined"]:
        assert lever["estimate"][p] is None and lever["stderr"][p] is None
    cal_doc = json.loads(json.dumps(calibration_to_dict(d.calibration), allow_nan=False))
    (tv,) = [t for t in cal_doc["terms"] if t["name"] == "lever_arm"]
    assert set(tv["undetermined"]) == set(lever["undetermined"])
    assert all(tv["params"][p] is None for p in tv["undetermined"])
    back = calibration_from_dict(cal_doc)
    assert np.isfinite(back.terms[0].params).all()
