"""Ferraris calibration (Ferraris, Grimaldi, Parvis 1995), as the imucal package does it.

Session: six static poses (``x_p``/``x_a``: +x axis up/down, same for y and z) and three
rotations (``x_rot``, ``y_rot``, ``z_rot``: one full turn about that axis, by hand). Sections
are sample index ranges ``[start, end)``.

Equations (imucal's ``FerrarisCalibration.compute``, rewritten in the affine form of
:class:`calib_core.calibration.Calibration`, with specific force in g):

* accel: ``U_p``, ``U_n`` = mean raw accel of the +/- poses as columns (x, y, z);
  ``U_d = U_p - U_n``. The +/- poses apply +/-1 g along one axis, so the whole scale and
  misalignment matrix is ``K_a = 2 U_d^-1`` (imucal's ``inv(R_a) inv(K_a)`` is the same
  product, split into scale and rotation); the bias is ``b_a = diag(U_p + U_n) / 2`` (Ferraris
  eq. 20: only the diagonal is used) and ``f0 = -K_a b_a``.
* gyro bias ``b_g`` = mean of all samples of the six static poses (sample-weighted).
* gyro g-sensitivity, raw gyro per g: ``S = (V_p - V_n) / 2`` with ``V`` the mean raw gyro of
  the poses (imucal's ``K_ga`` times g).
* rotations: ``W`` columns = sum over each rotation of ``(G - b_g - S f) / rate`` with ``f``
  the calibrated accel; the rotations are ``expected_angle`` (-360 deg: clockwise, imucal's
  default) about x, y, z, so ``K_g = expected_angle * W^-1`` and ``w0 = -K_g b_g``.
* the g-sensitivity becomes the catalogue term ``gyro_g_sensitivity`` with matrix
  ``K_g S`` (deg/s per g), subtracted by ``Calibration.apply``.

Gravity: imucal converts with g = 9.81 m/s^2 (its default ``grav``); the importer divides
m/s^2 input by the same value, so ``K_a`` here equals imucal's ``inv(R_a) inv(K_a)`` and
``9.81 * f0`` its ``-inv(R_a) inv(K_a) b_a``: the calibrated outputs agree to rounding.
Inverses are solves (``np.linalg.solve``) on 3x3 systems.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field

import numpy as np

from calib_core.calibration import Calibration, TermValue
from calib_core.effects import SensingGeometry
from calib_core.errors import DesignError

STATIC_SECTIONS = ("x_p", "x_a", "y_p", "y_a", "z_p", "z_a")
ROTATION_SECTIONS = ("x_rot", "y_rot", "z_rot")
FERRARIS_SECTIONS = STATIC_SECTIONS + ROTATION_SECTIONS


@dataclass(frozen=True)
class FerrarisFit:
    """Ferraris calibration with the intermediate quantities and checks."""

    calibration: Calibration
    accel_bias_raw: np.ndarray  # b_a, raw accel unit
    gyro_bias_raw: np.ndarray  # b_g, raw gyro unit
    gyro_g_raw: np.ndarray  # S, raw gyro per g (3x3, column j: pose along axis j)
    rotation_integrals_raw: np.ndarray  # W, raw gyro * s (3x3, column j: rotation about j)
    pose_f: dict[str, np.ndarray] = field(default_factory=dict)  # calibrated mean f per pose, g
    pose_w: dict[str, np.ndarray] = field(default_factory=dict)  # calibrated mean w per pose, deg/s
    rotation_angles_deg: dict[str, np.ndarray] = field(default_factory=dict)  # calibrated integral

    def summary(self) -> dict[str, float]:
        """Scalar checks: |f| error of the static poses (mg; the affine fit forces only the
        diagonal), largest off-axis static f (mg), residual static rate (deg/s)."""
        norms = np.array([np.linalg.norm(v) for v in self.pose_f.values()])
        off = []
        for name, v in self.pose_f.items():
            i = "xyz".index(name[0])
            off.append(np.abs(np.delete(v, i)).max())
        return {
            "static_norm_err_max_mg": float(1e3 * np.abs(norms - 1).max()),
            "static_offaxis_max_mg": float(1e3 * max(off)),
            "static_rate_max_dps": float(max(np.abs(v).max() for v in self.pose_w.values())),
        }


def _check_sections(sections: Mapping[str, tuple[int, int]], n: int) -> None:
    missing = [s for s in FERRARIS_SECTIONS if s not in sections]
    if missing:
        raise DesignError(
            "E_FERRARIS_SECTIONS", f"section list lacks {', '.join(missing)}", undetermined=tuple(missing)
        )
    for name in FERRARIS_SECTIONS:
        a, b = sections[name]
        if not (0 <= a < b <= n):
            raise DesignError(
                "E_FERRARIS_SECTIONS", f"section {name} = [{a}, {b}) is empty or outside 0..{n}"
            )


def ferraris_calibration(
    G: np.ndarray,
    A: np.ndarray,
    sections: Mapping[str, tuple[int, int]],
    rate_hz: float,
    expected_angle_deg: float = -360.0,
    gyro_unit: str = "deg/s",
    accel_unit: str = "g",
    g_local: float = 9.81,
    metadata: dict | None = None,
) -> FerrarisFit:
    """Ferraris calibration of raw gyro ``G`` (n, 3) and raw accel ``A`` (n, 3, in ``g`` or a
    raw unit) from the section list; returns a :class:`FerrarisFit` whose ``calibration`` has
    ``kind="ferraris"``. ``g_local`` is only stored (for m/s^2 output); the fit is in g."""
    G = np.asarray(G, float)
    A = np.asarray(A, float)
    _check_sections(sections, len(G))
    sl = {k: slice(*sections[k]) for k in FERRARIS_SECTIONS}
    mean_a = {k: A[sl[k]].mean(axis=0) for k in STATIC_SECTIONS}
    mean_g = {k: G[sl[k]].mean(axis=0) for k in STATIC_SECTIONS}

    U_p = np.column_stack([mean_a[f"{ax}_p"] for ax in "xyz"])
    U_n = np.column_stack([mean_a[f"{ax}_a"] for ax in "xyz"])
    U_d = U_p - U_n
    cond = np.linalg.cond(U_d)
    if not np.isfinite(cond) or cond > 1e8:
        raise DesignError(
            "E_FERRARIS_POSES",
            f"static poses do not span three axes (cond {cond:.3g})",
            undetermined=("K_a",),
        )
    K_a = np.linalg.solve(U_d.T, 2.0 * np.eye(3)).T  # K_a U_d = 2 I
    b_a = np.diag(U_p + U_n) / 2.0
    f0 = -K_a @ b_a

    b_g = np.vstack([G[sl[k]] for k in STATIC_SECTIONS]).mean(axis=0)
    S = (
        np.column_stack([mean_g[f"{ax}_p"] for ax in "xyz"])
        - np.column_stack([mean_g[f"{ax}_a"] for ax in "xyz"])
    ) / 2.0

    W = np.zeros((3, 3))
    for j, name in enumerate(ROTATION_SECTIONS):
        f = A[sl[name]] @ K_a.T + f0
        W[:, j] = (G[sl[name]] - b_g - f @ S.T).sum(axis=0) / rate_hz
    if np.linalg.cond(W) > 1e8:
        raise DesignError("E_FERRARIS_ROTATIONS", "rotations do not span three axes", undetermined=("K_g",))
    K_g = np.linalg.solve(W.T, expected_angle_deg * np.eye(3)).T  # K_g W = angle I
    w0 = -K_g @ b_g
    # the catalogue's g-sensitivity is per gyro, along its own sensing direction (rows of
    # A_g); the body-frame rate error K_g S f is A_g^-1 (A_g K_g S) f
    A_g = SensingGeometry.from_gains(K_g, K_a).gyro_axes
    term = TermValue("gyro_g_sensitivity", (A_g @ K_g @ S).reshape(-1))
    cal = Calibration(
        K_g=K_g,
        w0=w0,
        K_a=K_a,
        f0=f0,
        gyro_unit=gyro_unit,
        accel_unit=accel_unit,
        terms=(term,),
        g_local=g_local,
        kind="ferraris",
        metadata={
            "method": "Ferraris et al. 1995 (imucal's equations)",
            "expected_angle_deg": expected_angle_deg,
            "rate_hz": rate_hz,
            "sections": {k: list(map(int, v)) for k, v in sections.items()},
            **(metadata or {}),
        },
    )

    pose_f, pose_w = {}, {}
    for k in STATIC_SECTIONS:
        w, f = cal.apply(G[sl[k]], A[sl[k]])
        pose_f[k], pose_w[k] = f.mean(axis=0), w.mean(axis=0)
    angles = {}
    for k in ROTATION_SECTIONS:
        w, _ = cal.apply(G[sl[k]], A[sl[k]])
        angles[k] = w.sum(axis=0) / rate_hz
    return FerrarisFit(cal, b_a, b_g, S, W, pose_f, pose_w, angles)


def section_pose_means(
    t: np.ndarray, G: np.ndarray, A: np.ndarray, sections: Mapping[str, tuple[int, int]], trim: int = 0
):
    """Raw means per static section of a Ferraris session (name, start, end, count, t_mid,
    gx..az and their std), for model discovery on real data; see
    :func:`calib_core.models.field.static_detection.static_pose_means`."""
    from calib_core.models.field.static_detection import static_pose_means

    names = [k for k in STATIC_SECTIONS if k in sections]
    return static_pose_means(t, G, A, [sections[k] for k in names], names=names, trim=trim)
