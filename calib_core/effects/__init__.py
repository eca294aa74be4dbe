"""The catalogue of physical effects that model discovery searches, one module per effect.

Each effect module owns its term (columns through the sensing geometry, parameter names and
units, label), its realistic size and how to hide it in the independent physics simulator
(:meth:`EffectTerm.physics_knobs`), what excites it, and the variable its report figure plots
against. Adding an effect is one module plus its import below; nothing else names effects.
"""

# the built-in catalogue: importing a module registers its effect
from calib_core.effects import (  # noqa: F401
    accel_scale_nonlinearity,
    bias_time_drift,
    earth_rate,
    gyro_g_sensitivity,
    gyro_scale_asymmetry,
    gyro_scale_nonlinearity,
    lever_arm,
    thermal_bias_drift,
    thermal_scale_drift,
)
from calib_core.effects.base import (
    ACCEL,
    CHANNELS,
    DEG,
    GYRO,
    THERMAL_REF_C,
    EffectTerm,
    FigureVariable,
    MotionContext,
    SensingGeometry,
    catalogue,
    get_effect,
    register_effect,
    skew,
    total_error,
    unregister_effect,
)

__all__ = [
    "ACCEL",
    "CHANNELS",
    "DEG",
    "GYRO",
    "THERMAL_REF_C",
    "EffectTerm",
    "FigureVariable",
    "MotionContext",
    "SensingGeometry",
    "catalogue",
    "get_effect",
    "register_effect",
    "skew",
    "total_error",
    "unregister_effect",
]
