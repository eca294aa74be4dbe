"""The built-in catalogue of physical effects (see :mod:`calib_core.effects`).

Each term is small on purpose: its regressors say how the effect enters the six physical
channels, its parameter units are chosen so that realistic values are of order 1.
"""
from __future__ import annotations

import numpy as np

from calib_core.effects import EffectTerm, MotionContext, register_effect

DEG = np.pi / 180.0


def skew(v: np.ndarray) -> np.ndarray:
    """Cross-product matrices of rows of v: (n, 3) -> (n, 3, 3), skew(a) @ b = a x b."""
    v = np.atleast_2d(v)
    # filled in place (nine stacks of columns cost more than the matrices, called per session)
    out = np.zeros((len(v), 3, 3), dtype=np.result_type(v.dtype, np.float64))
    out[:, 0, 1], out[:, 0, 2] = -v[:, 2], v[:, 1]
    out[:, 1, 0], out[:, 1, 2] = v[:, 2], -v[:, 0]
    out[:, 2, 0], out[:, 2, 1] = -v[:, 1], v[:, 0]
    return out


@register_effect
class LeverArmTerm(EffectTerm):
    """Accelerometer size effect (zhang2017): accelerometer i sits at r_i (mm) from the
    rotation centre and senses f + w x (w x r_i) + dw/dt x r_i along its own axis."""

    name = "lever_arm"
    description = "accelerometer size effect (lever arm), w x (w x r_i) + dw/dt x r_i"
    param_names = tuple(f"r{i}{c}" for i in (1, 2, 3) for c in "xyz")
    param_units = ("mm",) * 9

    def regressors(self, ctx: MotionContext) -> np.ndarray:
        w = ctx.w * DEG
        a = ctx.dwdt * DEG
        om = skew(w)
        m = om @ om + skew(a)  # (n,3,3): acceleration at r is m @ r
        scale = 1e-3 / ctx.g_local  # mm -> m, m/s^2 -> g
        out = np.zeros((len(ctx), 6, 9))
        for i in range(3):  # accelerometer i only senses its own component at its own r_i
            out[:, 3 + i, 3 * i : 3 * i + 3] = m[:, i, :] * scale
        return out


@register_effect
class GyroScaleNonlinearityTerm(EffectTerm):
    """Quadratic and cubic scale-factor terms per gyro axis, rate in units of 1000 deg/s.
    The +/- difference method cancels the quadratic term; the +/- sum does not."""

    name = "gyro_scale_nonlinearity"
    description = "gyro scale-factor nonlinearity, quadratic and cubic in rate"
    param_names = ("q_x", "q_y", "q_z", "c_x", "c_y", "c_z")
    param_units = ("deg/s per (1000 deg/s)^2",) * 3 + ("deg/s per (1000 deg/s)^3",) * 3

    def regressors(self, ctx: MotionContext) -> np.ndarray:
        u = ctx.w / 1000.0
        out = np.zeros((len(ctx), 6, 6))
        for i in range(3):
            out[:, i, i] = u[:, i] ** 2
            out[:, i, 3 + i] = u[:, i] ** 3
        return out


@register_effect
class GyroScaleAsymmetryTerm(EffectTerm):
    """Different scale factor for positive and negative rates: scale(+) - scale(-) = a (ppm)."""

    name = "gyro_scale_asymmetry"
    description = "gyro scale-factor asymmetry between positive and negative rates"
    param_names = ("a_x", "a_y", "a_z")
    param_units = ("ppm",) * 3

    def regressors(self, ctx: MotionContext) -> np.ndarray:
        out = np.zeros((len(ctx), 6, 3))
        for i in range(3):
            out[:, i, i] = 0.5e-6 * np.abs(ctx.w[:, i])
        return out


@register_effect
class GyroGSensitivityTerm(EffectTerm):
    """Gyro rate error proportional to specific force: e_g = G f, G in deg/s per g (3x3)."""

    name = "gyro_g_sensitivity"
    description = "gyro g-sensitivity, rate error proportional to specific force"
    param_names = tuple(f"G{i}{j}" for i in "xyz" for j in "xyz")
    param_units = ("deg/s per g",) * 9

    def regressors(self, ctx: MotionContext) -> np.ndarray:
        out = np.zeros((len(ctx), 6, 9))
        for i in range(3):
            out[:, i, 3 * i : 3 * i + 3] = ctx.f
        return out


@register_effect
class AccelScaleNonlinearityTerm(EffectTerm):
    """Quadratic scale-factor term per accelerometer axis: e_a,i = k2_i f_i^2 (mg per g^2)."""

    name = "accel_scale_nonlinearity"
    description = "accelerometer scale-factor nonlinearity, quadratic in specific force"
    param_names = ("k2_x", "k2_y", "k2_z")
    param_units = ("mg per g^2",) * 3

    def regressors(self, ctx: MotionContext) -> np.ndarray:
        out = np.zeros((len(ctx), 6, 3))
        for i in range(3):
            out[:, 3 + i, i] = 1e-3 * ctx.f[:, i] ** 2
        return out


THERMAL_REF_C = 25.0


@register_effect
class ThermalBiasDriftTerm(EffectTerm):
    """Bias linear in temperature (per degC from 25 degC) on all six channels; where no
    temperature is recorded, linear in time since session start (per hour) instead."""

    name = "thermal_bias_drift"
    description = "bias drift with temperature (or with time when no temperature is recorded)"
    param_names = ("d_gx", "d_gy", "d_gz", "d_ax", "d_ay", "d_az")
    # the regressor is temperature when recorded, else time: the unit says both
    param_units = ("deg/s per degC (per hour without temp_c)",) * 3 + (
        "mg per degC (per hour without temp_c)",) * 3

    def regressors(self, ctx: MotionContext) -> np.ndarray:
        x = np.where(np.isfinite(ctx.temp_c), ctx.temp_c - THERMAL_REF_C, ctx.t / 3600.0)
        out = np.zeros((len(ctx), 6, 6))
        for ch in range(6):
            out[:, ch, ch] = x * (1e-3 if ch >= 3 else 1.0)
        return out
