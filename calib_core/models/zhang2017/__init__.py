"""zhang2017 (Zhang et al. 2017): comprehensive accelerometer calibration.

- :mod:`calib_core.models.zhang2017.static`: the 15-parameter static model (scale, zero bias,
  nine installation angles) and its round trip to the 12-parameter affine form;
- :mod:`calib_core.models.zhang2017.lever_arm`: the lever arms of the three accelerometers
  (one joint least squares over the dynamic steps), the paper's closed form for contrast, and
  the compensation of the specific force.

The simulation truth in this form is :mod:`calib_core.sim.accel_unit`.
"""

from calib_core.models.zhang2017.lever_arm import (
    CERTIFY_MARGIN,
    LEVER_NAMES,
    PROJECTIONS,
    UNDETERMINED_RCOND,
    LeverArmFit,
    LeverArmInputs,
    compensate_specific_force,
    fit_lever_arm,
    fit_lever_arm_from,
    fit_lever_arm_from_stack,
    lever_arm_estimate,
    lever_arm_inputs,
    lever_arm_inputs_stack,
    lever_matrix,
    paper_lever_arm,
)
from calib_core.models.zhang2017.static import (
    ANGLE_NAMES,
    AXES,
    BIAS_NAMES,
    SCALE_NAMES,
    STATIC_TESTS,
    AccelStaticFit,
    C_from_angles,
    affine_from_parts,
    affine_to_static,
    angles_from_C,
    decompose_static,
    fit_accel_static,
    fit_accel_static_stack,
    static_matrix,
    static_to_affine,
)

__all__ = [
    "ANGLE_NAMES",
    "AXES",
    "AccelStaticFit",
    "BIAS_NAMES",
    "CERTIFY_MARGIN",
    "C_from_angles",
    "LEVER_NAMES",
    "LeverArmFit",
    "LeverArmInputs",
    "PROJECTIONS",
    "SCALE_NAMES",
    "STATIC_TESTS",
    "UNDETERMINED_RCOND",
    "affine_from_parts",
    "affine_to_static",
    "angles_from_C",
    "compensate_specific_force",
    "decompose_static",
    "fit_accel_static",
    "fit_accel_static_stack",
    "fit_lever_arm",
    "fit_lever_arm_from",
    "fit_lever_arm_from_stack",
    "lever_arm_estimate",
    "lever_arm_inputs",
    "lever_arm_inputs_stack",
    "lever_matrix",
    "paper_lever_arm",
    "static_matrix",
    "static_to_affine",
]
