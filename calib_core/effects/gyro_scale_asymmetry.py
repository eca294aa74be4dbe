"""Gyro scale-factor asymmetry: the scale factor differs for positive and negative inputs,
scale(+) - scale(-) = a (ppm), in the gyro's own input u = a . w."""

from __future__ import annotations

import numpy as np

from calib_core.effects.base import (
    EffectTerm,
    FigureVariable,
    MotionContext,
    SensingGeometry,
    random_sign,
    register_effect,
    sensor_zeros,
)


@register_effect
class GyroScaleAsymmetry(EffectTerm):
    name = "gyro_scale_asymmetry"
    description = "gyro scale-factor asymmetry between positive and negative rates"
    param_names = ("a_x", "a_y", "a_z")
    param_units = ("ppm",) * 3
    excited_by = "rotation steps of both signs (an error even in rate, |u|)"
    max_useful_stderr = 1e4

    def sensor_regressors(self, ctx: MotionContext, geometry: SensingGeometry) -> np.ndarray:
        u = geometry.sensor_inputs(ctx)[0]
        out = sensor_zeros(len(ctx), 3)
        for i in range(3):
            out[:, i, i] = 0.5e-6 * np.abs(u[:, i])
        return out

    def realistic(self, rng, scale=1.0):
        """One gyro, 300-1000 ppm."""
        theta = np.zeros(3)
        i = int(rng.integers(3))
        theta[i] = random_sign(rng) * rng.uniform(300.0, 1000.0) * scale
        return theta, f"gyro {'xyz'[i]}"

    def physics_knobs(self, theta):
        return {("gyro", i): {"asym": float(theta[i]) * 1e-6} for i in range(3) if theta[i]}

    def figure_variable(self, ctx, channel):
        return FigureVariable("rate on the gyro's own axis", "deg/s", ctx.w[:, channel % 3])
