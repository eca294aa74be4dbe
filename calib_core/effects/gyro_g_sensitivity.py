"""Gyro g-sensitivity: gyro i's rate error is g_i . f (deg/s per g of body specific force)."""

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
class GyroGSensitivity(EffectTerm):
    name = "gyro_g_sensitivity"
    description = "gyro g-sensitivity, rate error proportional to specific force"
    param_names = tuple(f"G{i}{j}" for i in "xyz" for j in "xyz")
    param_units = ("deg/s per g",) * 9
    excited_by = "steps in several orientations (multiposition), gravity along each axis"
    max_useful_stderr = 0.05

    def sensor_regressors(self, ctx: MotionContext, geometry: SensingGeometry) -> np.ndarray:
        out = sensor_zeros(len(ctx), 9)
        for i in range(3):
            out[:, i, 3 * i : 3 * i + 3] = ctx.f
        return out

    def realistic(self, rng, scale=1.0):
        """1-3 random entries of G, 0.01-0.05 deg/s per g."""
        theta = np.zeros(9)
        k = rng.choice(9, size=int(rng.integers(1, 4)), replace=False)
        theta[k] = [random_sign(rng) * rng.uniform(0.01, 0.05) for _ in k]
        return theta * scale, "G" + ",".join(self.param_names[j][1:] for j in sorted(k))

    def physics_knobs(self, theta):
        G = np.asarray(theta, float).reshape(3, 3)
        return {("gyro", i): {"g_sens": tuple(float(x) for x in G[i])} for i in range(3) if np.any(G[i])}

    def figure_variable(self, ctx, channel):
        j = int(np.argmax(np.std(ctx.f, axis=0)))
        return FigureVariable(f"specific force along {'xyz'[j]}", "g", ctx.f[:, j])
