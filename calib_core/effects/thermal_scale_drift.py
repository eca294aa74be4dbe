"""Scale factor linear in temperature: each sensor's output is its input times
(1 + c (T - 25 degC)), c in ppm/degC (xu2016's k_g33 drift between repetitions). Needs the
temperature column: without it no step excites the term."""

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
class ThermalScaleDrift(EffectTerm):
    name = "thermal_scale_drift"
    description = "scale factor drift with temperature"
    param_names = ("tc_gx", "tc_gy", "tc_gz", "tc_ax", "tc_ay", "tc_az")
    param_units = ("ppm/degC",) * 6
    excited_by = (
        "a temperature change during the session (warm-up) while the input is "
        "large: fast rates for the gyros, several orientations for the accelerometers"
    )
    max_useful_stderr = 100.0

    def sensor_regressors(self, ctx: MotionContext, geometry: SensingGeometry) -> np.ndarray:
        dT = np.where(np.isfinite(ctx.temp_c), ctx.temp_c - THERMAL_REF_C, 0.0)
        u_g, u_a = geometry.sensor_inputs(ctx)
        u = np.hstack([u_g, u_a])  # (n, 6) each sensor's own input
        out = sensor_zeros(len(ctx), 6)
        idx = np.arange(6)
        out[:, idx, idx] = 1e-6 * dT[:, None] * u
        return out

    def realistic(self, rng, scale=1.0):
        """One sensor, 30-300 ppm/degC."""
        theta = np.zeros(6)
        c = int(rng.integers(6))
        theta[c] = random_sign(rng) * rng.uniform(30.0, 300.0)
        return theta * scale, f"sensor {CHANNELS[c]}"

    def physics_knobs(self, theta):
        t = np.asarray(theta, float)
        return {
            ("gyro" if i < 3 else "accel", i % 3): {"scale_tc_ppm": float(t[i])} for i in range(6) if t[i]
        }

    def figure_variable(self, ctx, channel):
        u = (ctx.w if channel < 3 else ctx.f)[:, channel % 3]
        dT = np.where(np.isfinite(ctx.temp_c), ctx.temp_c - THERMAL_REF_C, 0.0)
        unit = "deg/s degC" if channel < 3 else "g degC"
        return FigureVariable("input x (temperature - 25 degC)", unit, u * dT)
