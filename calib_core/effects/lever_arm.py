"""Accelerometer size effect (lever arm, zhang2017): accelerometer i sits at r_i (mm) from the
rotation centre and senses a_i . (f + w x (w x r_i) + dw/dt x r_i) along its own sensing
direction a_i. Every component of r_i that the steps make visible is estimated: the one
along a_i directly (centripetal acceleration of rotations about the other axes), the others
through the misalignment of a_i at high rate and through tilted rotation axes."""

from __future__ import annotations

import numpy as np

from calib_core.effects.base import (
    DEG,
    EffectTerm,
    FigureVariable,
    MotionContext,
    SensingGeometry,
    register_effect,
    sensor_zeros,
    skew,
)


@register_effect
class LeverArm(EffectTerm):
    name = "lever_arm"
    description = "accelerometer size effect (lever arm), a_i . (w x (w x r_i) + dw/dt x r_i)"
    param_names = tuple(f"r{i}{c}" for i in (1, 2, 3) for c in "xyz")
    param_units = ("mm",) * 9
    excited_by = (
        "rotation steps (centripetal acceleration grows with the rate squared); "
        "components along the rotation axis need rotations about other axes"
    )
    max_useful_stderr = 2.0  # mm: a realistic arm is 4-16 mm

    def sensor_regressors(self, ctx: MotionContext, geometry: SensingGeometry) -> np.ndarray:
        om = skew(ctx.w * DEG)
        m = (om @ om + skew(ctx.dwdt * DEG)) * (1e-3 / ctx.g_local)  # r (mm) -> g at r
        out = sensor_zeros(len(ctx), 9)
        for i in range(3):  # accelerometer i senses its own r_i along its own direction
            out[:, 3 + i, 3 * i : 3 * i + 3] = np.einsum("j,njk->nk", geometry.accel_axes[i], m)
        return out

    def realistic(self, rng, scale=1.0):
        """One accelerometer 4-16 mm from the rotation centre, random direction."""
        theta = np.zeros(9)
        i = int(rng.integers(3))
        v = rng.normal(size=3)
        theta[3 * i : 3 * i + 3] = v / np.linalg.norm(v) * rng.uniform(4.0, 16.0) * scale
        return theta, f"accelerometer {'xyz'[i]}"

    def physics_knobs(self, theta):
        r = np.asarray(theta, float).reshape(3, 3)
        return {
            ("accel", i): {"position_mm": tuple(float(x) for x in r[i])} for i in range(3) if np.any(r[i])
        }

    def figure_variable(self, ctx, channel):
        return FigureVariable("rate squared", "(deg/s)^2", np.sum(ctx.w**2, axis=1))
