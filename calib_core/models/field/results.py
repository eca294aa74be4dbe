"""A field calibration (:func:`calib_core.models.field.joint.fit_field`) as the fit results every
calibration of a unit lists: the affine ``K_g, w0`` and ``K_a, f0`` under the turntable
fits' parameter names (``k_g11..``, ``w0_x..``, ``k_a11..``, ``f0_x..``, models ``gyro`` and
``accel``) with standard errors, so that field-calibrated units are averaged over their
recordings, stored, compared and flagged like turntable units; plus the recording's figures
of merit (model ``field_fit``).

The standard errors of the affine form come from the covariance of IMU-TK's parameters
(accel: from the |f| fit; gyro: including the accelerometer's, see
``field_joint._with_accel_uncertainty``) through the Jacobian of the map (delta method,
central differences)."""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Any

import numpy as np

from calib_core.calibration import Calibration, TermValue
from calib_core.models.field.imu_tk import accel_matrix, gyro_matrix
from calib_core.models.field.joint import FieldFigures, FieldJointFit
from calib_core.models.pipeline import calibration_from_unit
from calib_core.models.xu2016 import F0_NAMES, K_A_NAMES, K_G_NAMES, W0_NAMES
from calib_core.results import ParamBlock, RepetitionCalibration, UnitCalibration, params_of_blocks

FIGURE_NAMES = ("norm_rms_mg", "angle_rms_deg", "n_poses", "n_moves")
FIGURE_UNITS = ("mg", "deg", "poses", "moves")


@dataclass(frozen=True)
class FieldGyroFit:
    """The gyro of a field calibration in the affine form (deg/s per raw unit, deg/s)."""

    K: np.ndarray
    w0: np.ndarray
    K_stderr: np.ndarray
    w0_stderr: np.ndarray
    raw_unit: str
    model: str = "gyro"

    def param_blocks(self) -> list[ParamBlock]:
        return [
            (self.model, K_G_NAMES, self.K, self.K_stderr, f"deg/s per {self.raw_unit}"),
            (self.model, W0_NAMES, self.w0, self.w0_stderr, "deg/s"),
        ]

    def parameters(self):
        return params_of_blocks(self.param_blocks())

    def to_dict(self) -> dict[str, Any]:
        return {
            "K_g": self.K.tolist(),
            "w0": self.w0.tolist(),
            "stderr": {"K_g": self.K_stderr.tolist(), "w0": self.w0_stderr.tolist()},
            "method": "field",
        }


@dataclass(frozen=True)
class FieldAccelFit:
    """The accelerometer of a field calibration in the affine form (g per raw unit, g)."""

    K: np.ndarray
    f0: np.ndarray
    K_stderr: np.ndarray
    f0_stderr: np.ndarray
    raw_unit: str
    model: str = "accel"

    def param_blocks(self) -> list[ParamBlock]:
        return [
            (self.model, K_A_NAMES, self.K, self.K_stderr, f"g per {self.raw_unit}"),
            (self.model, F0_NAMES, self.f0, self.f0_stderr, "g"),
        ]

    def parameters(self):
        return params_of_blocks(self.param_blocks())

    def to_dict(self) -> dict[str, Any]:
        return {
            "K_a": self.K.tolist(),
            "f0": self.f0.tolist(),
            "stderr": {"K_a": self.K_stderr.tolist(), "f0": self.f0_stderr.tolist()},
            "method": "field",
        }


@dataclass(frozen=True)
class FieldFigureFit:
    """A recording's figures of merit after calibration (in-sample: static |f| error RMS
    over the poses, gravity-direction error RMS over the usable moves) and how many poses and
    moves were used; no standard errors."""

    values: np.ndarray  # FIGURE_NAMES
    model: str = "field_fit"

    def param_blocks(self) -> list[ParamBlock]:
        nan = np.full(1, np.nan)
        return [
            (self.model, (n,), self.values[i : i + 1], nan, u)
            for i, (n, u) in enumerate(zip(FIGURE_NAMES, FIGURE_UNITS))
        ]

    def parameters(self):
        return params_of_blocks(self.param_blocks())

    def to_dict(self) -> dict[str, Any]:
        return {n: float(v) for n, v in zip(FIGURE_NAMES, self.values)}


def _propagate(fn, p: np.ndarray, cov: np.ndarray | None, n_used: int) -> np.ndarray:
    """Standard errors of ``fn(p)`` (a flat vector) from ``cov`` of the first ``n_used``
    entries of ``p``: central differences, step a hundredth of each standard error."""
    y0 = fn(p)
    if cov is None or not np.all(np.isfinite(cov[:n_used, :n_used])):
        return np.full(y0.shape, np.nan)
    J = np.zeros((y0.size, n_used))
    for i in range(n_used):
        h = max(1e-2 * float(np.sqrt(max(cov[i, i], 0.0))), 1e-12 * max(abs(p[i]), 1.0))
        hi, lo = p.copy(), p.copy()
        hi[i] += h
        lo[i] -= h
        J[:, i] = (fn(hi) - fn(lo)) / (2 * h)
    c = J @ cov[:n_used, :n_used] @ J.T
    return np.sqrt(np.clip(np.diag(c), 0, None))


def affine_fits(fit: FieldJointFit) -> tuple[FieldGyroFit, FieldAccelFit]:
    """``fit.calibration``'s ``K_g, w0, K_a, f0`` with their standard errors."""
    cal = fit.calibration
    g_local = cal.g_local

    def accel_affine(p):
        M, b = accel_matrix(p)
        K = M / g_local
        return np.concatenate([K.ravel(), -K @ b])

    def gyro_affine(p):
        K = np.degrees(gyro_matrix(p[:9]))
        return np.concatenate([K.ravel(), -K @ p[9:12]])

    se_a = _propagate(accel_affine, np.asarray(fit.accel.params, float), fit.accel.cov, 9)
    se_g = _propagate(gyro_affine, np.asarray(fit.gyro.params, float), fit.gyro.cov, 12)
    gyro = FieldGyroFit(cal.K_g, cal.w0, se_g[:9].reshape(3, 3), se_g[9:], cal.gyro_unit)
    accel = FieldAccelFit(cal.K_a, cal.f0, se_a[:9].reshape(3, 3), se_a[9:], cal.accel_unit)
    return gyro, accel


def figure_fit(figures: FieldFigures, move_ok) -> FieldFigureFit:
    s = figures.summary("", move_ok)
    return FieldFigureFit(np.array([float(s[n]) for n in FIGURE_NAMES]))


def field_unit_calibration(
    lot: str, unit: str, reps: list[RepetitionCalibration], recordings: list[Calibration]
) -> tuple[UnitCalibration, Calibration]:
    """A field unit's calibration: the mean of its recordings' affine forms (``reps``, as
    turntable repetitions are averaged), kind ``field``, with the optional gyro terms every
    recording's calibration (``recordings``) kept, averaged; a term only some kept is left
    out."""
    uc = UnitCalibration.from_reps(lot, unit, reps)
    names = set.intersection(*({tv.name for tv in c.terms} for c in recordings)) if recordings else set()
    terms = tuple(
        TermValue(n, np.mean([next(tv.params for tv in c.terms if tv.name == n) for c in recordings], axis=0))
        for n in sorted(names)
    )
    base = calibration_from_unit(uc)
    applied = replace(
        base,
        terms=terms,
        kind="field",
        metadata={
            **base.metadata,
            "model": "field (hand-held poses)",
            "recordings": [r.provenance["recording"] for r in reps],
        },
    )
    return uc, applied
