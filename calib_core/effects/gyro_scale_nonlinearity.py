"""Gyro scale-factor nonlinearity: quadratic and cubic in the gyro's own input u = a . w, in
units of 1000 deg/s. The +/- difference method of xu2016 cancels the quadratic part; steps
entering one by one do not."""

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

FULL_SCALE_DPS = np.array([300.0, 300.0, 3600.0])  # the rated range of the simulated units


@register_effect
class GyroScaleNonlinearity(EffectTerm):
    name = "gyro_scale_nonlinearity"
    description = "gyro scale-factor nonlinearity, quadratic and cubic in the gyro's own input"
    param_names = ("q_x", "q_y", "q_z", "c_x", "c_y", "c_z")
    param_units = ("deg/s per (1000 deg/s)^2",) * 3 + ("deg/s per (1000 deg/s)^3",) * 3
    excited_by = "rotation steps over the rate range, both signs (quadratic: even in rate)"
    max_useful_stderr = 1e3

    def sensor_regressors(self, ctx: MotionContext, geometry: SensingGeometry) -> np.ndarray:
        u = geometry.sensor_inputs(ctx)[0] / 1000.0
        out = sensor_zeros(len(ctx), 6)
        for i in range(3):
            out[:, i, i] = u[:, i] ** 2
            out[:, i, 3 + i] = u[:, i] ** 3
        return out

    def realistic(self, rng, scale=1.0):
        """One gyro; quadratic and cubic parts each 0.02-0.06 % of full scale at full scale
        (MEMS datasheets: 0.1 % FS), random signs."""
        theta = np.zeros(6)
        i = int(rng.integers(3))
        fs = FULL_SCALE_DPS[i]
        u = fs / 1000.0
        theta[i] = random_sign(rng) * rng.uniform(2e-4, 6e-4) * fs / u**2
        theta[3 + i] = random_sign(rng) * rng.uniform(2e-4, 6e-4) * fs / u**3
        return theta * scale, f"gyro {'xyz'[i]}"

    def physics_knobs(self, theta):
        t = np.asarray(theta, float)
        # the simulator's polynomial is u + k2 u^2 + k3 u^3 with u in deg/s
        return {("gyro", i): {"k2": t[i] * 1e-6, "k3": t[3 + i] * 1e-9} for i in range(3) if t[i] or t[3 + i]}

    def figure_variable(self, ctx, channel):
        return FigureVariable("rate on the gyro's own axis", "deg/s", ctx.w[:, channel % 3])
