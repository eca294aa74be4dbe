"""zhang2017's 15-parameter static accelerometer model (paper section 2.1, eq. 1-9).

Accelerometer i has a scale factor k_i (raw unit per g), a zero bias u_i0 = k_i B_i (raw unit)
and a sensitive axis c_i, the unit vector of direction cosines cos(theta_ij) against the body
axes (column i of the paper's C_ab, eq. 9):

    u_i = k_i (c_i . f + B_i)   (eq. 2, 4)
    i.e.  A = M f + u0,   M = diag(k) C^T   (eq. 5, 7)

M and u0 (12 numbers) are estimated by linear least squares; k_i = |M_i| and c_i = M_i / k_i
recover the 15 parameters exactly (3 of the 15 are fixed by |c_i| = 1). The affine form of
xu2016 (f = K_a A + f0) is K_a = M^-1, f0 = -M^-1 u0.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any, ClassVar

import numpy as np

from calib_core.errors import DesignError
from calib_core.models.display import ModelDisplay, register_display
from calib_core.results import Param, ParamBlock, params_of_blocks
from calib_core.steps import StepMeans, stack_field

AXES = "xyz"
STATIC_TESTS = ("multiposition", "stationary")
ANGLE_NAMES = tuple(f"theta_{a}{b}" for a in AXES for b in AXES)  # row-major, theta_ij
SCALE_NAMES = tuple(f"k_{a}" for a in AXES)
BIAS_NAMES = tuple(f"u0_{a}" for a in AXES)


# -- conversions between the 15-parameter form and the paper's 12-parameter affine form --------
def static_matrix(scale: np.ndarray, C: np.ndarray) -> np.ndarray:
    """M = diag(k) C^T: raw output per g; row i is k_i c_i."""
    return np.asarray(scale, float)[:, None] * np.asarray(C, float).T


def decompose_static(M: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Exact decomposition M -> (k, C): k_i = |M_i|, column i of C is M_i / k_i (for a stack
    of matrices (..., 3, 3), each)."""
    M = np.asarray(M, float)
    k = np.linalg.norm(M, axis=-1)
    if np.any(k == 0) or not np.all(np.isfinite(k)):
        raise DesignError("E_ZERO_SCALE", "a row of the static matrix is zero: no scale factor")
    return k, np.swapaxes(M / k[..., None], -1, -2)


def angles_from_C(C: np.ndarray) -> np.ndarray:
    """theta_ij (deg) = angle between sensitive axis i and body axis j; row i = accelerometer i."""
    return np.degrees(np.arccos(np.clip(np.asarray(C, float).T, -1.0, 1.0)))


def C_from_angles(angles_deg: np.ndarray, normalise: bool = True) -> np.ndarray:
    """Direction cosines from theta_ij (row i = accelerometer i) -> C (columns = c_i).

    Published angles are rounded, so cos(theta_i.) is not exactly a unit vector: normalised."""
    c = np.cos(np.radians(np.asarray(angles_deg, float)))  # row i = c_i
    if normalise:
        c = c / np.linalg.norm(c, axis=1, keepdims=True)
    return c.T


def static_to_affine(fit: AccelStaticFit) -> tuple[np.ndarray, np.ndarray]:
    """(K_a, f0) of f = K_a A + f0 from the 15 parameters."""
    return affine_from_parts(fit.scale, fit.bias, fit.C)


def affine_from_parts(scale, bias, C) -> tuple[np.ndarray, np.ndarray]:
    M = static_matrix(scale, C)
    K_a = np.linalg.inv(M)  # 3x3 closed form: the run-time model avoids any inverse
    return K_a, -K_a @ np.asarray(bias, float)


def affine_to_static(K_a: np.ndarray, f0: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(k, u0, C) from (K_a, f0): M = K_a^-1, u0 = -M f0, then the exact decomposition."""
    M = np.linalg.inv(np.asarray(K_a, float))
    u0 = -M @ np.asarray(f0, float)
    k, C = decompose_static(M)
    return k, u0, C


# -- static fit ----------------------------------------------------------------------------------
@dataclass(frozen=True)
class AccelStaticFit:
    """The 15 parameters of zhang2017 with standard errors (model ``accel_static``)."""

    scale: np.ndarray  # (3,) k_i, raw unit per g
    bias: np.ndarray  # (3,) u_i0 = k_i B_i, raw unit
    C: np.ndarray  # (3,3) column i = sensitive axis c_i (direction cosines)
    scale_stderr: np.ndarray
    bias_stderr: np.ndarray
    angles_stderr: np.ndarray  # (3,3) deg, row i = accelerometer i
    channel_cov: np.ndarray  # (3,4,4) covariance of (M_i, u0_i) per channel, raw units
    condition_number: float  # of the design [f, 1]
    residual_rms_g: float  # pooled over the three channels, in g
    dof: int
    n_steps: int
    unit: str = "g"  # raw accelerometer unit
    g_local: float = 9.80665
    model: ClassVar[str] = "accel_static"

    @property
    def angles_deg(self) -> np.ndarray:
        return angles_from_C(self.C)

    @property
    def M(self) -> np.ndarray:
        return static_matrix(self.scale, self.C)

    def affine(self) -> tuple[np.ndarray, np.ndarray]:
        return static_to_affine(self)

    def sensed_along_axes(self, A_raw: np.ndarray) -> np.ndarray:
        """(u_i - u0_i) / k_i: specific force along each sensitive axis, g, (n,3)."""
        return (np.atleast_2d(A_raw) - self.bias) / self.scale

    def apply(self, A_raw: np.ndarray) -> np.ndarray:
        """Static compensation only: f = (C^T)^-1 (u - u0)/k, (n,3) g."""
        return np.linalg.solve(self.C.T, self.sensed_along_axes(A_raw).T).T

    def parameters(self) -> list[Param]:
        return params_of_blocks(self.param_blocks())

    def param_blocks(self) -> list[ParamBlock]:
        return [
            (self.model, SCALE_NAMES, self.scale, self.scale_stderr, f"{self.unit}/g"),
            (self.model, BIAS_NAMES, self.bias, self.bias_stderr, self.unit),
            (self.model, ANGLE_NAMES, self.angles_deg, self.angles_stderr, "deg"),
        ]

    def to_dict(self) -> dict[str, Any]:
        return {
            "scale": self.scale.tolist(),
            "bias": self.bias.tolist(),
            "angles_deg": self.angles_deg.tolist(),
            "stderr": {
                "scale": self.scale_stderr.tolist(),
                "bias": self.bias_stderr.tolist(),
                "angles_deg": self.angles_stderr.tolist(),
            },
            "units": {"scale": f"{self.unit}/g", "bias": self.unit, "angles_deg": "deg"},
            "condition_number": float(self.condition_number),
            "residual_rms_g": float(self.residual_rms_g),
            "n_steps": int(self.n_steps),
        }


def fit_accel_static(sm: StepMeans, tests: tuple[str, ...] = STATIC_TESTS) -> AccelStaticFit:
    """15-parameter static model from the static steps with known specific force.

    Per channel i, A_i = M_i . f_ref + u0_i by least squares; the residual variance is
    pooled over the three channels in g (same accelerometer type: equal noise in physical
    units), which gives 3(n-4) degrees of freedom instead of n-4. Standard errors of k, u0 and
    the angles follow from the LS covariance through the Jacobian of the decomposition.
    """
    return fit_accel_static_stack([sm], tests)[0]


def fit_accel_static_stack(
    sms: Sequence[StepMeans], tests: tuple[str, ...] = STATIC_TESTS
) -> list[AccelStaticFit]:
    """:func:`fit_accel_static` of sessions that share one step layout (the repetitions of a
    unit), together: session r's fit is the one ``fit_accel_static(sms[r])`` returns, bit for
    bit. Raises the DesignError of the first session that has one."""
    sm = sms[0]  # the layout every session shares
    rows = sm.rows_of_test(*tests)
    n = len(rows)
    if n < 5:
        raise DesignError(
            "E_TOO_FEW_STATIC_STEPS",
            f"{n} static steps ({', '.join(tests)}); the 12-parameter fit needs "
            "at least 5 to estimate its noise",
            ("accel_static",),
        )
    # eq. 5: A = M f + u0, per channel i A_i = [f 1] . (M_i, u0_i): one design X = [f_ref 1]
    X = np.hstack([sm.f_ref[rows], np.ones((n, 1))])
    _, sv, Vt = np.linalg.svd(X, full_matrices=False)
    if sv[-1] <= 1e-9 * sv[0]:
        raise DesignError(
            "E_STATIC_RANK",
            "static steps do not span three specific-force "
            "directions and a constant: M and u0 are not determined",
            ("accel_static",),
        )
    A = stack_field(sms, "accel")[:, rows]  # (R, n, 3)
    # lstsq per session (not a cached pseudo-inverse): the lever arms are fitted on this
    # model's residuals, where a last-bit change of M shows as 1e-8 of a zero lever arm;
    # nor one lstsq of all sessions' columns, which rounds differently
    beta = np.stack([np.linalg.lstsq(X, a, rcond=None)[0] for a in A])  # column i: (M_i, u0_i)
    M = np.swapaxes(beta[:, :3], 1, 2)
    u0 = beta[:, 3]
    # eq. 7, 9: M = diag(k) C^T, so k_i = |M_i| and c_i = M_i / k_i (a unit vector)
    k, C = decompose_static(M)
    # noise pooled over the three channels in g (one accelerometer type: equal noise in g)
    resid = A - X @ beta
    dof_ch = n - 4
    var_g = ((resid / k[:, None, :]) ** 2).reshape(len(sms), -1).sum(axis=1) / (3 * dof_ch)
    unscaled = (Vt.T / sv**2) @ Vt  # (X^T X)^-1 from the SVD, never inverting X^T X
    channel_cov = unscaled * (var_g[:, None] * k**2)[:, :, None, None]  # (R,3,4,4)
    cov_m = channel_cov[:, :, :3, :3]
    u0_se = np.sqrt(channel_cov[:, :, 3, 3])
    # standard errors through the Jacobian of the decomposition: dk_i/dM_i = c_i
    k_se = np.sqrt(np.einsum("rji,rijk,rki->ri", C, cov_m, C))
    # dc_i/dM_i = (I - c_i c_i^T) / k_i; d theta_ij / d M_i = -(row j of it) / sin theta_ij
    Ct = np.swapaxes(C, 1, 2)  # row i = c_i
    dc = (np.eye(3) - Ct[:, :, :, None] * Ct[:, :, None, :]) / k[:, :, None, None]
    sin_t = np.sqrt(np.maximum(1.0 - Ct**2, 1e-300))
    g = -dc / sin_t[:, :, :, None]
    ang_se = np.degrees(np.sqrt(np.einsum("rijk,rikl,rijl->rij", g, cov_m, g)))
    return [
        AccelStaticFit(
            scale=k[r],
            bias=u0[r],
            C=C[r],
            scale_stderr=k_se[r],
            bias_stderr=u0_se[r],
            angles_stderr=ang_se[r],
            channel_cov=channel_cov[r],
            condition_number=float(sv[0] / sv[-1]),
            residual_rms_g=float(np.sqrt(var_g[r])),
            dof=3 * dof_ch,
            n_steps=n,
            unit=sm.accel_unit,
            g_local=sm.g_local,
        )
        for r in range(len(sms))
    ]


# How the reports show this model (calib_core.models.display): zero biases, scale factors,
# installation angles.
register_display(
    ModelDisplay(
        "accel_static",
        "Accelerometer static model (zhang2017)",
        tuple(f"u0_{a}" for a in "xyz")
        + tuple(f"k_{a}" for a in "xyz")
        + tuple(f"theta_{a}{b}" for a in "xyz" for b in "xyz"),
        rank=2,
        key_title="Accelerometer static model (zhang2017, 15 parameters)",
    )
)
