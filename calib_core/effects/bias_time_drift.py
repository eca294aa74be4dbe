"""Bias linear in time since the session started (per hour) on each of the six sensors: a
trend that is not temperature (ageing of the turn-on transient, a slow drift of the
electronics). With a warm-up ramp recorded, time and temperature are told apart by the
curvature of the ramp (:mod:`calib_core.discovery.identifiability` says when they are not)."""

from __future__ import annotations

import numpy as np

from calib_core.effects.base import (
    CHANNELS,
    EffectTerm,
    FigureVariable,
    MotionContext,
    SensingGeometry,
    random_sign,
    register_effect,
    sensor_zeros,
)


@register_effect
class BiasTimeDrift(EffectTerm):
    name = "bias_time_drift"
    description = "bias drift with time since the session started"
    param_names = ("r_gx", "r_gy", "r_gz", "r_ax", "r_ay", "r_az")
    param_units = ("deg/s per hour",) * 3 + ("mg per hour",) * 3
    excited_by = "a session long enough for the drift to show (minutes)"
    max_useful_stderr = 0.5

    def sensor_regressors(self, ctx: MotionContext, geometry: SensingGeometry) -> np.ndarray:
        x = np.asarray(ctx.t, float) / 3600.0
        out = sensor_zeros(len(ctx), 6)
        for ch in range(6):
            out[:, ch, ch] = x * (1e-3 if ch >= 3 else 1.0)
        return out

    def realistic(self, rng, scale=1.0):
        """One sensor: gyro 0.25-1 deg/s per hour or accelerometer 2.5-10 mg per hour (over a
        six-minute protocol as much as thermal_bias_drift's realistic size over its warm-up)."""
        theta = np.zeros(6)
        c = int(rng.integers(6))
        theta[c] = random_sign(rng) * (rng.uniform(0.25, 1.0) if c < 3 else rng.uniform(2.5, 10.0))
        return theta * scale, f"sensor {CHANNELS[c]}"

    def physics_knobs(self, theta):
        t = np.asarray(theta, float)
        out = {("gyro", i): {"bias_per_h": float(t[i])} for i in range(3) if t[i]}
        out.update({("accel", i): {"bias_per_h": float(t[3 + i]) * 1e-3} for i in range(3) if t[3 + i]})
        return out

    def figure_variable(self, ctx, channel):
        return FigureVariable("time since session start", "s", ctx.t)
