"""Bias linear in temperature (per degC from 25 degC) on each of the six sensors. Needs the
temperature column: without it no step excites the term (a drift in time is
:mod:`calib_core.effects.bias_time_drift`)."""

from __future__ import annotations

import numpy as np

from calib_core.effects.base import (
    CHANNELS,
    THERMAL_REF_C,
    EffectTerm,
    FigureVariable,
    MotionContext,
    SensingGeometry,
    random_sign,
    register_effect,
    sensor_zeros,
)


@register_effect
class ThermalBiasDrift(EffectTerm):
    name = "thermal_bias_drift"
    description = "bias drift with temperature"
    param_names = ("d_gx", "d_gy", "d_gz", "d_ax", "d_ay", "d_az")
    param_units = ("deg/s per degC",) * 3 + ("mg per degC",) * 3
    excited_by = "a temperature change during the session (warm-up), recorded in temp_c"
    max_useful_stderr = 0.05

    def sensor_regressors(self, ctx: MotionContext, geometry: SensingGeometry) -> np.ndarray:
        x = np.where(np.isfinite(ctx.temp_c), ctx.temp_c - THERMAL_REF_C, 0.0)
        out = sensor_zeros(len(ctx), 6)
        for ch in range(6):
            out[:, ch, ch] = x * (1e-3 if ch >= 3 else 1.0)
        return out

    def realistic(self, rng, scale=1.0):
        """One sensor: gyro 0.005-0.02 deg/s/degC or accelerometer 0.05-0.2 mg/degC."""
        theta = np.zeros(6)
        c = int(rng.integers(6))
        theta[c] = random_sign(rng) * (rng.uniform(0.005, 0.02) if c < 3 else rng.uniform(0.05, 0.2))
        return theta * scale, f"sensor {CHANNELS[c]}"

    def physics_knobs(self, theta):
        t = np.asarray(theta, float)
        out = {("gyro", i): {"bias_tc": float(t[i])} for i in range(3) if t[i]}
        out.update({("accel", i): {"bias_tc": float(t[3 + i]) * 1e-3} for i in range(3) if t[3 + i]})
        return out

    def figure_variable(self, ctx, channel):
        return FigureVariable("temperature", "degC", ctx.temp_c)
