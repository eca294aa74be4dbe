"""A tri-axis accelerometer unit in zhang2017's form (scale, bias, sensitive axes, lever arms),
the truth its Monte Carlo and navigation simulations are drawn from: noise-free raw outputs,
and the same unit as a :class:`calib_core.sim.simulator.MimuTruth` with the lever arm
projected on each sensitive axis (paper eq. 13)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from calib_core.effects import MotionContext, SensingGeometry, get_effect
from calib_core.models.zhang2017 import LEVER_NAMES, affine_from_parts, angles_from_C, lever_matrix
from calib_core.sim.simulator import MimuTruth


class SensitiveAxisLeverArm:
    """Lever arm projected on each accelerometer's own sensitive axis (paper eq. 13), as an
    error on the body-frame specific force: e = (C^T)^-1 [c_i^T W r_i]_i: the catalogue's
    lever arm (:mod:`calib_core.effects.lever_arm`) on the sensing geometry of C, whatever
    geometry the caller passes (the truth carries its own)."""

    name = "lever_arm_sensitive_axis"
    param_names = LEVER_NAMES

    def __init__(self, C: np.ndarray):
        self.C = np.asarray(C, float)
        self._geometry = SensingGeometry(np.eye(3), (self.C / np.linalg.norm(self.C, axis=0)).T)

    def regressors(self, ctx: MotionContext, geometry: SensingGeometry | None = None) -> np.ndarray:
        return get_effect("lever_arm").regressors(ctx, self._geometry)

    def error(
        self, ctx: MotionContext, theta: np.ndarray, geometry: SensingGeometry | None = None
    ) -> np.ndarray:
        return self.regressors(ctx) @ np.asarray(theta, dtype=float)


@dataclass(frozen=True)
class AccelUnitTruth:
    """A tri-axis accelerometer unit in the zhang2017 form, for simulation."""

    scale: np.ndarray  # (3,) raw per g
    bias: np.ndarray  # (3,) raw
    C: np.ndarray  # (3,3) columns = sensitive axes
    lever_arm_mm: np.ndarray  # (3,3) row i = r_i
    unit: str = "V"
    g_local: float = 9.80665

    @property
    def angles_deg(self) -> np.ndarray:
        return angles_from_C(self.C)

    def raw(self, f_g: np.ndarray, w_dps: np.ndarray, dwdt_dps2: np.ndarray | None = None) -> np.ndarray:
        """Noise-free raw outputs u_i = k_i (c_i . (f + W r_i)) + u0_i, (n,3)."""
        f = np.atleast_2d(f_g)
        W = lever_matrix(
            np.broadcast_to(np.atleast_2d(w_dps), f.shape),
            None if dwdt_dps2 is None else np.broadcast_to(np.atleast_2d(dwdt_dps2), f.shape),
        )
        at_r = f[:, None, :] + np.einsum("nab,ib->nia", W, self.lever_arm_mm) * (
            1e-3 / self.g_local
        )  # (n, i, 3): specific force at accelerometer i
        along = np.einsum("ai,nia->ni", self.C, at_r)
        return self.scale * along + self.bias

    def to_mimu_truth(self, **kw) -> MimuTruth:
        """The same unit as a :class:`calib_core.sim.simulator.MimuTruth` (affine K_a, f0 and the
        sensitive-axis lever-arm effect). Gyros ideal unless given; gyro full scale widened so
        that constant-rate steps are not dropped."""
        K_a, f0 = affine_from_parts(self.scale, self.bias, self.C)
        base = dict(
            K_a=K_a,
            f0=f0,
            accel_unit=self.unit,
            g_local=self.g_local,
            gyro_range_dps=(2000.0, 2000.0, 4000.0),
            effects=((SensitiveAxisLeverArm(self.C), self.lever_arm_mm.ravel()),),
        )
        base.update(kw)
        return MimuTruth(**base)
