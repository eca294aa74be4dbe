"""Accelerometer scale-factor nonlinearity: quadratic in the accelerometer's own input
u = a . f (mg per g^2)."""

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
class AccelScaleNonlinearity(EffectTerm):
    name = "accel_scale_nonlinearity"
    description = "accelerometer scale-factor nonlinearity, quadratic in its own input"
    param_names = ("k2_x", "k2_y", "k2_z")
    param_units = ("mg per g^2",) * 3
    excited_by = (
        "orientations with gravity partly along the axis (multiposition at "
        "intermediate angles): at 0 and +/-1 g the quadratic is a scale and bias"
    )
    max_useful_stderr = 1.0

    def sensor_regressors(self, ctx: MotionContext, geometry: SensingGeometry) -> np.ndarray:
        u = geometry.sensor_inputs(ctx)[1]
        out = sensor_zeros(len(ctx), 3)
        for i in range(3):
            out[:, 3 + i, i] = 1e-3 * u[:, i] ** 2
        return out

    def realistic(self, rng, scale=1.0):
        """One accelerometer, 0.3-1 mg/g^2."""
        theta = np.zeros(3)
        i = int(rng.integers(3))
        theta[i] = random_sign(rng) * rng.uniform(0.3, 1.0) * scale
        return theta, f"accelerometer {'xyz'[i]}"

    def physics_knobs(self, theta):
        return {("accel", i): {"k2": float(theta[i]) * 1e-3} for i in range(3) if theta[i]}

    def figure_variable(self, ctx, channel):
        return FigureVariable("specific force on the accelerometer's own axis", "g", ctx.f[:, channel % 3])
