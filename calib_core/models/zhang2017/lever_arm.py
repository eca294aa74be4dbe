"""zhang2017's dynamic model: the lever arms (size effect) of the three accelerometers
(paper sections 2.2-2.3) and the compensation of the specific force (eq. 16-17).

Accelerometer i sits at r_i (mm) from the rotation centre and senses its own axis' component
of the specific force at r_i:

    u_i = k_i (c_i . (f + W r_i) + B_i),    W = [w x]^2 + [dw/dt x]      (eq. 11-13)

With the static model (:mod:`calib_core.models.zhang2017.static`) known, y_i = (u_i - u0_i) /
k_i - c_i . f = c_i^T W r_i (eq. 12, the lever term f_iL) is linear in r_i;
:func:`fit_lever_arm` solves it for all nine components in one least squares over every
dynamic step and rate. The paper's closed form (its eq. 24, :func:`paper_lever_arm`) divides by
the direction cosines, which are near zero for the off-diagonal components: kept for contrast.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any, ClassVar

import numpy as np
from scipy.linalg.lapack import dgeqp3 as _geqp3

from calib_core.effects import DEG, skew
from calib_core.errors import DesignError
from calib_core.models.display import ModelDisplay, register_display
from calib_core.models.zhang2017.static import AXES, AccelStaticFit
from calib_core.results import Param, ParamBlock, params_of_blocks
from calib_core.steps import StepMeans, stack_field

# a lever-arm direction whose pivoted-QR diagonal is below this fraction of the largest one
# is reported as undetermined (with x/y/z-up steps only, the off-diagonal components are seen
# through direction cosines of ~0.01: the paper's "distortion")
UNDETERMINED_RCOND = 0.05
LEVER_NAMES = tuple(f"r{i + 1}{a}" for i in range(3) for a in AXES)


def lever_matrix(w_dps: np.ndarray, dwdt_dps2: np.ndarray | None = None) -> np.ndarray:
    """W = [w x]^2 + [dw/dt x] in rad^2/s^2 (or rad/s^2), (n,3,3)."""
    om = skew(np.atleast_2d(w_dps) * DEG)
    W = om @ om
    if dwdt_dps2 is not None:
        W = W + skew(np.atleast_2d(dwdt_dps2) * DEG)
    return W


@dataclass(frozen=True)
class LeverArmFit:
    """Positions r_i (mm) of the three accelerometers (model ``lever_arm``).

    Row i of ``lever_arm_mm`` is r_i. Components the steps cannot determine are NaN (value and
    stderr) and named in ``undetermined``; the determined ones were fitted with those fixed
    at zero (their coupling through the direction cosines, ~1 %, biases what remains)."""

    lever_arm_mm: np.ndarray  # (3,3)
    stderr: np.ndarray  # (3,3), includes the static-fit uncertainty
    condition_number: float  # of the fitted (determined) design, block-diagonal over i
    condition_number_full: float  # of the design with all nine components
    undetermined: tuple[str, ...]
    reasons: dict[str, str]
    residual_rms_g: float
    dof: int
    n_steps: int
    rate_source: str  # "w_ref" or "gyro"
    projection: str = "sensitive_axis"  # or "body_axis" (the catalogue's LeverArmTerm model)
    model: ClassVar[str] = "lever_arm"
    # applied (calib_core.models.applied): the catalogue's lever arm, when fully determined
    applied_term: ClassVar[str] = "lever_arm"
    document_key: ClassVar[str] = "lever_arm_mm"
    document_unit: ClassVar[str] = "mm"

    def applied_values(self) -> np.ndarray:
        """Row i is r_i, mm (raveled: the catalogue's parameter order); NaN: undetermined."""
        return np.asarray(self.lever_arm_mm, dtype=float)

    def applied_stderr(self) -> np.ndarray:
        return np.asarray(self.stderr, dtype=float)

    @property
    def r_mm(self) -> np.ndarray:
        """Alias of ``lever_arm_mm`` (the name the pipeline uses)."""
        return self.lever_arm_mm

    @property
    def r_for_compensation(self) -> np.ndarray:
        """Undetermined components contribute nothing (treated as 0 mm)."""
        return np.nan_to_num(self.lever_arm_mm, nan=0.0)

    def parameters(self) -> list[Param]:
        return params_of_blocks(self.param_blocks())

    def param_blocks(self) -> list[ParamBlock]:
        return [(self.model, LEVER_NAMES, self.lever_arm_mm, self.stderr, "mm")]

    def to_dict(self) -> dict[str, Any]:
        def lst(a):
            return [[None if not np.isfinite(v) else float(v) for v in row] for row in a]

        return {
            "lever_arm_mm": lst(self.lever_arm_mm),
            "stderr": lst(self.stderr),
            "condition_number": float(self.condition_number),
            "condition_number_full": (
                float(self.condition_number_full) if np.isfinite(self.condition_number_full) else None
            ),
            "undetermined": list(self.undetermined),
            "reasons": dict(self.reasons),
            "residual_rms_g": float(self.residual_rms_g),
            "n_steps": int(self.n_steps),
            "rate_source": self.rate_source,
            "projection": self.projection,
            "units": {"lever_arm_mm": "mm", "stderr": "mm"},
        }


def _step_rates(sm: StepMeans, gyro_K, gyro_w0) -> tuple[np.ndarray, str]:
    if gyro_K is None:
        return sm.w_ref, "w_ref"
    w0 = np.zeros(3) if gyro_w0 is None else np.asarray(gyro_w0, float)
    return sm.gyro @ np.asarray(gyro_K, float).T + w0, "gyro"


def _step_rates_stack(ds: Sequence[StepMeans], gyro_Ks, gyro_w0s) -> tuple[np.ndarray, list[str]]:
    """:func:`_step_rates` of each session, stacked (R, n, 3), and their sources. With gyro
    calibrations whose K^T are C-contiguous (the fits' K are transposed views), one stacked
    matmul: each matrix the same BLAS call as alone."""
    if gyro_Ks is not None and all(K is not None for K in gyro_Ks):
        KT = [np.asarray(K, float).T for K in gyro_Ks]
        if all(k.flags.c_contiguous for k in KT):
            w0 = np.stack(
                [
                    np.zeros(3) if gyro_w0s is None or gyro_w0s[r] is None else np.asarray(gyro_w0s[r], float)
                    for r in range(len(ds))
                ]
            )
            return stack_field(ds, "gyro") @ np.stack(KT) + w0[:, None, :], ["gyro"] * len(ds)
    rates = [
        _step_rates(d, None if gyro_Ks is None else gyro_Ks[r], None if gyro_w0s is None else gyro_w0s[r])
        for r, d in enumerate(ds)
    ]
    return np.stack([w for w, _ in rates]), [source for _, source in rates]


PROJECTIONS = ("sensitive_axis", "body_axis")


def fit_lever_arm(
    sm: StepMeans,
    static: AccelStaticFit,
    gyro_K=None,
    gyro_w0=None,
    rcond: float = UNDETERMINED_RCOND,
    projection: str = "sensitive_axis",
) -> LeverArmFit:
    """r_1, r_2, r_3 (mm) from the ``dynamic`` steps by one joint least squares.

    ``projection="sensitive_axis"`` (the paper, eq. 12-13): row (i, s) is
    y_is = (u_is - u0_i)/k_i - c_i . f_ref,s = c_i^T W_s r_i (1e-3/g: mm -> g).
    ``projection="body_axis"`` is the model of the catalogue's ``lever_arm`` term
    (:mod:`calib_core.effects.lever_arm`): the statically compensated body-frame
    specific force minus f_ref has component i = (W_s r_i)_i. The two differ by misalignment x
    lever term (~0.3 mm of r for 1 deg misalignment).

    The nine unknowns are solved together (block-diagonal design over the accelerometers);
    the residual variance is pooled in g over all rows. Standard errors add the static fit's
    uncertainty (u0, M enter y linearly) through the Jacobian of the solution. Components whose
    pivoted-QR diagonal falls below ``rcond`` of the largest in their block are undetermined.
    """
    if projection not in PROJECTIONS:
        raise ValueError(f"projection must be one of {PROJECTIONS}, got {projection!r}")
    return fit_lever_arm_from(lever_arm_inputs(sm, static, gyro_K, gyro_w0), rcond, projection)


@dataclass(frozen=True)
class LeverArmInputs:
    """What both projections of :func:`fit_lever_arm` share for one session: the dynamic
    steps, their rate matrices and the statically compensated specific force."""

    static: AccelStaticFit
    d: StepMeans  # the dynamic steps
    W: np.ndarray  # (n,3,3) lever matrices, g per mm
    K_a: np.ndarray  # M^-1
    f_hat: np.ndarray  # (n,3) statically compensated specific force, body frame
    source: str  # "w_ref" or "gyro"


def lever_arm_inputs(sm: StepMeans, static: AccelStaticFit, gyro_K=None, gyro_w0=None) -> LeverArmInputs:
    """The shared part of the lever-arm fit (compute once, fit both projections from it)."""
    return lever_arm_inputs_stack(
        [sm], [static], None if gyro_K is None else [gyro_K], None if gyro_w0 is None else [gyro_w0]
    )[0]


def lever_arm_inputs_stack(
    sms: Sequence[StepMeans], statics: Sequence[AccelStaticFit], gyro_Ks=None, gyro_w0s=None
) -> list[LeverArmInputs]:
    """:func:`lever_arm_inputs` of sessions that share one step layout (with their static
    fits and, optionally, gyro calibrations), computed together; item r is bit for bit
    ``lever_arm_inputs(sms[r], statics[r], gyro_Ks[r], gyro_w0s[r])``."""
    rows = sms[0].rows_of_test("dynamic")  # the layout's: every session's
    if len(rows) == 0:
        raise DesignError(
            "E_NO_DYNAMIC_STEPS", "no dynamic steps: lever arms need constant-rate rotation", LEVER_NAMES
        )
    ds = [sm.select(rows) for sm in sms]
    w, sources = _step_rates_stack(ds, gyro_Ks, gyro_w0s)  # (R, n, 3)
    R, n = w.shape[:2]
    g_per_mm = 1e-3 / np.array([static.g_local for static in statics])
    W = lever_matrix(w.reshape(R * n, 3)).reshape(R, n, 3, 3) * g_per_mm[:, None, None, None]
    K_a = np.linalg.inv(np.stack([static.M for static in statics]))
    bias = np.stack([static.bias for static in statics])
    # statically compensated specific force, body frame
    f_hat = (stack_field(ds, "accel") - bias[:, None, :]) @ np.swapaxes(K_a, 1, 2)
    return [LeverArmInputs(statics[r], ds[r], W[r], K_a[r], f_hat[r], sources[r]) for r in range(R)]


def lever_arm_estimate(
    inputs: LeverArmInputs, rcond: float = UNDETERMINED_RCOND, projection: str = "sensitive_axis"
) -> np.ndarray:
    """``fit_lever_arm_from(...).r_mm`` (the same numbers) without the standard errors, for
    callers that only apply the lever arms (the pipeline's body-axis fit)."""
    return fit_lever_arm_from(inputs, rcond, projection, _estimate_only=True)


def fit_lever_arm_from(
    inputs: LeverArmInputs,
    rcond: float = UNDETERMINED_RCOND,
    projection: str = "sensitive_axis",
    _estimate_only: bool = False,
) -> LeverArmFit:
    """:func:`fit_lever_arm` on precomputed :func:`lever_arm_inputs`."""
    return fit_lever_arm_from_stack([inputs], rcond, projection, _estimate_only)[0]


def fit_lever_arm_from_stack(
    inputs: Sequence[LeverArmInputs],
    rcond: float = UNDETERMINED_RCOND,
    projection: str = "sensitive_axis",
    estimate_only: bool = False,
) -> list:
    """:func:`fit_lever_arm_from` of sessions that share one step layout (their
    :func:`lever_arm_inputs_stack`): item r is bit for bit ``fit_lever_arm_from(inputs[r])``
    (with ``estimate_only``, its ``r_mm`` as :func:`lever_arm_estimate` gives it). The
    sessions' block-diagonal solves run together when every component of every session is
    determined (the usual case), else each session alone. Whether a component is determined
    is the pivoted QR's decision per block; it is taken from the blocks' singular values
    instead when they leave no doubt (:func:`_certify_determined`), without the 3 R QRs."""
    if projection not in PROJECTIONS:
        raise ValueError(f"projection must be one of {PROJECTIONS}, got {projection!r}")
    designs = _lever_designs(inputs, projection)
    certified = _certify_determined(designs, rcond)
    if certified is not None:
        return _fit_all_determined(
            inputs, [_all_kept(Xb, yb) for Xb, yb in designs], projection, estimate_only, certified
        )
    blocks = [_lever_blocks(x, rcond, projection, design) for x, design in zip(inputs, designs)]
    determined = [len(b.cols) == 9 for b in blocks]
    if all(determined):
        return _fit_all_determined(inputs, blocks, projection, estimate_only)
    return [
        _fit_all_determined([x], [b], projection, estimate_only)[0]
        if all_determined
        else _fit_joint(x, b, projection, estimate_only)
        for x, b, all_determined in zip(inputs, blocks, determined)
    ]


# How far above ``rcond`` a block's sigma_min / sigma_max must be for the pivoted QR to keep
# all of its columns without running it (:func:`_certify_determined`).
CERTIFY_MARGIN = 2.0


def _certify_determined(designs: Sequence[tuple[np.ndarray, np.ndarray]], rcond: float):
    """The stacked blocks and their SVD, (Xb (R,3,n,3), yb (R,3,n), (U, s, Vt)), when every
    block of every session certainly keeps its three columns in :func:`_lever_blocks`'
    pivoted QR; else None (then the QR decides).

    Why it is certain: every diagonal entry of a pivoted QR's R of X is the distance of a
    column from the span of other columns, hence >= sigma_min(X), and the first is a column
    norm, <= sigma_max(X); the QR keeps column j when |R_jj| >= rcond |R_00|. With
    sigma_min >= CERTIFY_MARGIN * rcond * sigma_max, rounding in the QR and the SVD (relative
    ~1e-15) cannot bring a diagonal entry below the cut. The SVD is the one the all-determined
    fit takes of the same stacked blocks anyway, so the fit reuses it."""
    Xb = _stack_blocks([X for X, _ in designs])
    if Xb.shape[-2] < 3:  # fewer steps than components: never all determined
        return None
    try:
        svd = np.linalg.svd(Xb, full_matrices=False)
    except np.linalg.LinAlgError:
        return None
    s = svd[1]  # (R, 3, 3) descending
    with np.errstate(invalid="ignore"):
        sure = np.isfinite(s).all() and bool(
            ((s[..., 0] > 0) & (s[..., -1] >= CERTIFY_MARGIN * rcond * s[..., 0])).all()
        )
    if not sure:
        return None
    return Xb, _stack_blocks([y for _, y in designs]), svd


def _stack_blocks(per_session: list[np.ndarray]) -> np.ndarray:
    """The sessions' blocks stacked as _fit_all_determined stacks _LeverBlocks (each
    session's blocks stacked, then the sessions): the same array in the same memory layout
    (np.stack follows its inputs' layout, and the einsums that use the stack round by it).
    C-contiguous inputs stack to the same C-contiguous array in one call; a session's y
    (a transposed view in the body-axis projection) is made contiguous first, as stacking
    its 1-D rows did."""
    if per_session[0].ndim == 2:  # y (3, n): rows stacked -> C-contiguous
        return np.stack([np.ascontiguousarray(y) for y in per_session])
    if all(X.flags.c_contiguous for X in per_session):
        return np.stack(per_session)
    return np.stack([np.stack([X[i] for i in range(3)]) for X in per_session])


def _all_kept(Xb: np.ndarray, yb: np.ndarray) -> _LeverBlocks:
    """The _LeverBlocks of a session whose every component is determined (certified)."""
    keep = np.arange(3)
    return _LeverBlocks(
        [(i, Xb[i], yb[i], keep) for i in range(3)], [(i, j) for i in range(3) for j in range(3)], [], {}
    )


@dataclass(frozen=True)
class _LeverBlocks:
    """One session's lever-arm design, block i (accelerometer i): X (n,3), y (n,), and the
    components the rank-revealing QR keeps."""

    blocks: list  # (i, X_i, y_i, kept columns of block i)
    cols: list  # (i, j) of every kept component, block by block
    undetermined: list
    reasons: dict


def _lever_design(inputs: LeverArmInputs, projection: str) -> tuple[np.ndarray, np.ndarray]:
    """One session's lever-arm design, the three blocks (one per accelerometer) at once:
    X (3, n, 3) and y (3, n), block i the rows of accelerometer i."""
    static, d, W, f_hat = inputs.static, inputs.d, inputs.W, inputs.f_hat
    if projection == "sensitive_axis":
        # eq. 12-13: (u_i - u0_i)/k_i - c_i . f = c_i^T W r_i, the lever term f_iL
        k, C, u0 = static.scale, static.C, static.bias
        M = static.M
        Xb = np.einsum("ji,njk->ink", C, W)  # row s of block i: c_i^T W_s
        # f_ref @ M[i] one row at a time: the lever term is a small difference
        # of these, and d.f_ref @ M.T rounds differently (1e-10 of a near-zero lever arm)
        yb = (d.accel.T - u0[:, None] - np.stack([d.f_ref @ M[i] for i in range(3)])) / k[:, None]
    else:  # eq. 11 on the body axes: (K_a (u - u0) - f)_i = (W r_i)_i
        Xb = np.ascontiguousarray(W.transpose(1, 0, 2))  # block i: rows i of W_s
        yb = (f_hat - d.f_ref).T
    return Xb, yb


def _lever_designs(inputs: Sequence[LeverArmInputs], projection: str) -> list[tuple[np.ndarray, np.ndarray]]:
    """:func:`_lever_design` of each session, the sensitive-axis ones of sessions with the
    same number of dynamic steps computed together: the same einsum and the same
    matrix-vector products per session, stacked (the same numbers)."""
    if projection != "sensitive_axis" or len({len(x.d) for x in inputs}) > 1:
        return [_lever_design(x, projection) for x in inputs]
    C = np.stack([x.static.C for x in inputs])
    W = np.stack([x.W for x in inputs])
    M = np.stack([x.static.M for x in inputs])  # (R, 3, 3)
    k = np.stack([x.static.scale for x in inputs])
    u0 = np.stack([x.static.bias for x in inputs])
    f_ref = np.stack([x.d.f_ref for x in inputs])  # (R, n, 3)
    accel = np.stack([x.d.accel for x in inputs])
    Xb = np.einsum("rji,rnjk->rink", C, W)
    # f_ref @ M[i], one matrix-vector product per session and row of M, as _lever_design
    fM = (f_ref[:, None] @ M[..., None])[..., 0]  # (R, 3, n)
    yb = (np.swapaxes(accel, 1, 2) - u0[:, :, None] - fM) / k[:, :, None]
    return list(zip(Xb, yb))


def _lever_blocks(
    inputs: LeverArmInputs, rcond: float, projection: str, design: tuple[np.ndarray, np.ndarray] | None = None
) -> _LeverBlocks:
    """The blocks of :func:`_lever_design` (given, or built here) and the components each
    block's rank-revealing QR keeps."""
    Xb, yb = design if design is not None else _lever_design(inputs, projection)
    undetermined: list[str] = []
    reasons: dict[str, str] = {}
    blocks = []
    for i in range(3):
        X, y = Xb[i], yb[i]
        # rank-revealing QR: the trailing pivots with small diagonal are not observable
        # (LAPACK geqp3 directly: what scipy.linalg.qr(pivoting=True) runs, minus its checks)
        qr_, jpvt, _, _, info = _geqp3(X)
        if info != 0:  # pragma: no cover - LAPACK argument error
            raise DesignError("E_LEVER_RANK", f"pivoted QR failed (info={info})", LEVER_NAMES)
        piv = (jpvt - 1).tolist()
        diag = np.abs(qr_.diagonal()).tolist()
        if diag[0] > 0:
            keep = sorted(piv[: sum(1 for v in diag if v >= rcond * diag[0])])
        else:
            keep = []
        for j in sorted(set(range(3)) - set(keep)):
            name = LEVER_NAMES[3 * i + j]
            undetermined.append(name)
            # with fewer dynamic steps than components, the QR has fewer pivots than
            # columns: a component pivoted past them has no pivot (relative pivot 0)
            pos = piv.index(j)
            rel = diag[pos] / diag[0] if pos < len(diag) and diag[0] > 0 else 0.0
            reasons[name] = (
                f"not observable from these dynamic steps (relative pivot "
                f"{rel:.2g} < {rcond:g}); add steps with the rate off the body "
                "axes (protocols.dynamic_steps(tilted=True))"
            )
        blocks.append((i, X, y, np.asarray(keep, int)))
    # joint design (block-diagonal), determined columns only
    cols = [(i, j) for i, _, _, keep in blocks for j in keep]
    if not cols:
        raise DesignError("E_LEVER_RANK", "dynamic steps carry no centripetal signal", LEVER_NAMES)
    return _LeverBlocks(blocks, cols, undetermined, reasons)


def _fit_joint(inputs: LeverArmInputs, lb: _LeverBlocks, projection: str, estimate_only: bool = False):
    """The joint least squares of one session over its determined components (some
    component is undetermined: the blocks no longer have three columns each)."""
    static, d, K_a, f_hat = inputs.static, inputs.d, inputs.K_a, inputs.f_hat
    n = len(d)
    k, M = static.scale, static.M
    blocks, cols, undetermined, reasons = lb.blocks, lb.cols, lb.undetermined, lb.reasons
    r = np.full((3, 3), np.nan)
    se = np.full((3, 3), np.nan)
    A = np.zeros((3 * n, len(cols)))
    Y = np.concatenate([b[2] for b in blocks])
    for c, (i, j) in enumerate(cols):
        A[i * n : (i + 1) * n, c] = blocks[i][1][:, j]
    theta, *_ = np.linalg.lstsq(A, Y, rcond=None)
    if estimate_only:
        for c, (i, j) in enumerate(cols):
            r[i, j] = theta[c]
        return r
    resid = Y - A @ theta
    dof = 3 * n - len(cols)
    var_g = float(resid @ resid / dof) if dof > 0 else float("nan")
    # one SVD of A gives (A^T A)^-1, the pseudo-inverse and the condition number
    U, sva, Vt = np.linalg.svd(A, full_matrices=False)
    cov = ((Vt.T / sva**2) @ Vt) * var_g
    s_inv = np.divide(1.0, sva, where=sva > 1e-15 * sva.max(), out=np.zeros_like(sva))
    pinv = Vt.T @ (s_inv[:, None] * U.T)
    # propagate the static uncertainty, channel by channel (theta_ch = (M_ch, u0_ch)):
    # sensitive axis: dy_ch/dtheta_ch = -(f_s + e_ch,s M_ch / k_ch^2, 1) / k_ch (own block only);
    # body axis: y = K_a (A - u0) - f_ref, dy_i/dtheta_ch = -K_a[i, ch] (f_hat_s, 1)
    ones = np.ones((n, 1))
    for ch in range(3):
        dY = np.zeros((3 * n, 4))
        if projection == "sensitive_axis":
            e = blocks[ch][2] * k[ch]  # raw residual of the static model on these steps
            dY[ch * n : (ch + 1) * n] = -np.hstack([d.f_ref + np.outer(e, M[ch]) / k[ch] ** 2, ones]) / k[ch]
        else:
            for i in range(3):
                dY[i * n : (i + 1) * n] = -K_a[i, ch] * np.hstack([f_hat, ones])
        J = pinv @ dY
        cov = cov + J @ static.channel_cov[ch] @ J.T
    for c, (i, j) in enumerate(cols):
        r[i, j] = theta[c]
        se[i, j] = np.sqrt(cov[c, c])
    full = np.zeros((3 * n, 9))  # the design with all nine components
    for i, X, _, _ in blocks:
        full[i * n : (i + 1) * n, 3 * i : 3 * i + 3] = X
    svf = np.linalg.svd(full, compute_uv=False)
    return LeverArmFit(
        lever_arm_mm=r,
        stderr=se,
        condition_number=float(sva[0] / sva[-1]),
        condition_number_full=float(svf[0] / svf[-1]) if svf[-1] > 0 else float("inf"),
        undetermined=tuple(undetermined),
        reasons=reasons,
        residual_rms_g=float(np.sqrt(var_g)) if dof > 0 else float("nan"),
        dof=dof,
        n_steps=n,
        rate_source=inputs.source,
        projection=projection,
    )


def _fit_all_determined(
    inputs: Sequence[LeverArmInputs],
    blocks: Sequence[_LeverBlocks],
    projection: str,
    estimate_only: bool = False,
    stacked=None,
) -> list:
    """The joint fits of sessions whose every component is determined (the usual case,
    tilted steps), all sessions together.

    The design is then block diagonal with three (n,3) blocks, one per accelerometer, so one
    batched SVD of the blocks (of every session) gives what :func:`_fit_joint` gets from
    lstsq, two SVDs and a pseudo-inverse of the (3n,9) design: the same estimates and
    covariance, to rounding."""
    d = inputs[0].d
    R, n = len(inputs), len(d)
    k = np.stack([x.static.scale for x in inputs])  # (R,3)
    if stacked is not None:  # the blocks stacked and their SVD (_certify_determined)
        Xb, yb, (U, sb, Vt) = stacked
    else:
        Xb = np.stack([np.stack([b[1] for b in lb.blocks]) for lb in blocks])  # (R,3,n,3)
        yb = np.stack([np.stack([b[2] for b in lb.blocks]) for lb in blocks])  # (R,3,n)
        U, sb, Vt = np.linalg.svd(Xb, full_matrices=False)  # (R,3,n,3), (R,3,3), (R,3,3,3)
    V = np.swapaxes(Vt, -1, -2)
    pinv = V @ (np.swapaxes(U, -1, -2) / sb[..., :, None])  # block i = pinv(X_i)
    theta = np.einsum("rikn,rin->rik", pinv, yb)  # row i = r_i
    if estimate_only:
        return list(theta)
    resid = yb - np.einsum("rink,rik->rin", Xb, theta)
    dof = 3 * n - 9
    var_g = (resid**2).reshape(R, -1).sum(axis=1) / dof if dof > 0 else np.full(R, np.nan)
    cov4 = np.zeros((R, 3, 3, 3, 3))  # (r, i, j, i', j'): component (i,j) against (i',j')
    cov_blocks = ((V / sb[..., None, :] ** 2) @ Vt) * var_g[:, None, None, None]
    for i in range(3):
        cov4[:, i, :, i, :] = cov_blocks[:, i]
    # static uncertainty (see _fit_joint): sensitive axis, channel l moves block l only;
    # body axis, channel l moves block i by -K_a[i, l] pinv(X_i) (f_hat, 1)
    channel_cov = np.stack([x.static.channel_cov for x in inputs])  # (R,3,4,4)
    ones = np.ones((n, 1))
    if projection == "sensitive_axis":
        M = np.stack([x.static.M for x in inputs])
        e = yb * k[:, :, None]  # raw residuals of the static model, (R,3,n)
        dY = (
            np.concatenate(
                [
                    d.f_ref + e[..., None] * M[:, :, None, :] / k[..., None, None] ** 2,
                    np.broadcast_to(ones, (R, 3, n, 1)),
                ],
                axis=3,
            )
            / -k[..., None, None]
        )
        J = pinv @ dY  # (R,3,3,4): block l, channel l
        diag_blocks = np.einsum("rlai,rlij,rlbj->rlab", J, channel_cov, J)
        for i in range(3):
            cov4[:, i, :, i, :] += diag_blocks[:, i]
        cov = cov4.reshape(R, 9, 9)
    else:
        f_hat = np.stack([x.f_hat for x in inputs])
        K_a = np.stack([x.K_a for x in inputs])
        P = pinv @ np.concatenate([f_hat, np.broadcast_to(ones, (R, n, 1))], axis=2)[:, None]
        J = (-np.swapaxes(K_a, 1, 2)[..., None, None] * P[:, None]).reshape(R, 3, 9, 4)
        cov = cov4.reshape(R, 9, 9) + np.einsum("rlai,rlij,rlbj->rab", J, channel_cov, J)
    stderr = np.sqrt(np.diagonal(cov, axis1=1, axis2=2)).reshape(R, 3, 3)
    out = []
    for r, (x, lb) in enumerate(zip(inputs, blocks)):
        sv = sb[r].ravel()
        cond = float(sv.max() / sv.min()) if sv.min() > 0 else float("inf")
        out.append(
            LeverArmFit(
                lever_arm_mm=theta[r],
                stderr=stderr[r],
                condition_number=cond,
                condition_number_full=cond,
                undetermined=(),
                reasons=lb.reasons,
                residual_rms_g=float(np.sqrt(var_g[r])) if dof > 0 else float("nan"),
                dof=dof,
                n_steps=n,
                rate_source=x.source,
                projection=projection,
            )
        )
    return out


def paper_lever_arm(sm: StepMeans, static: AccelStaticFit) -> np.ndarray:
    """The paper's closed form (eq. 24), for contrast: r (mm), row i = accelerometer i.

    With D_u the output of accelerometer i along its axis at up-axis u rotating at w0, minus
    the same with the table at rest: r_ix = (D_x - D_y - D_z) / (2 w0^2 cos theta_ix), and
    cyclically. Averaged over the rates present with x-, y- and z-up (both signs). The rest
    outputs come from ``stationary`` steps when present, else from the static model. Divides
    by cos theta_ij of the off-diagonal angles (~0.01): this is what blows up.
    """
    y_all = static.sensed_along_axes(sm.accel)  # (n,3) g along each sensitive axis
    rest = {}
    for u in ("+x", "+y", "+z"):
        m = (sm.test == "stationary") & (sm.up_axis == u)
        if m.any():
            rest[u] = y_all[m].mean(axis=0)
        else:  # the static model's prediction of the rest output
            f = np.eye(3)["xyz".index(u[1])]
            rest[u] = static.C.T @ f
    dyn = sm.test == "dynamic"
    estimates = []
    for rate in np.unique(np.abs(sm.rate_dps[dyn])):
        D = {}
        for u in ("+x", "+y", "+z"):
            m = (
                dyn
                & (sm.up_axis == u)
                & np.isclose(np.abs(sm.rate_dps), rate)
                & np.isclose(np.abs(sm.w_ref @ np.eye(3)["xyz".index(u[1])]), rate)
            )
            if not m.any():
                break
            D[u] = y_all[m].mean(axis=0) - rest[u]
        if len(D) < 3:
            continue
        w2 = (rate * DEG) ** 2
        scale = static.g_local * 1e3 / (2.0 * w2)  # g -> m/s^2, m -> mm
        est = np.empty((3, 3))
        for i in range(3):
            c = static.C[:, i]
            Dx, Dy, Dz = D["+x"][i], D["+y"][i], D["+z"][i]
            est[i, 0] = (Dx - Dy - Dz) * scale / c[0]
            est[i, 1] = (Dy - Dx - Dz) * scale / c[1]
            est[i, 2] = (Dz - Dx - Dy) * scale / c[2]
        estimates.append(est)
    if not estimates:
        raise DesignError(
            "E_NO_AXIS_RATES", "the paper's formula needs the same rate with x-, y- and z-up", LEVER_NAMES
        )
    return np.mean(estimates, axis=0)


# -- compensation --------------------------------------------------------------------------------
def compensate_specific_force(
    static: AccelStaticFit,
    lever: LeverArmFit | None,
    A_raw: np.ndarray,
    w_dps: np.ndarray | None = None,
    dwdt_dps2: np.ndarray | None = None,
) -> np.ndarray:
    """Calibrated specific force at the rotation centre (g), (n,3): paper eq. 16-17.

    a_i = (u_i - u0_i)/k_i - c_i^T W r_i, f = (C^T)^-1 a, W = [w x]^2 + [dw/dt x] from the
    calibrated gyro rate and its derivative (for a ``body_axis`` fit: f = static model minus
    (W r_i)_i). ``lever=None`` gives the static model only; undetermined lever components
    count as zero."""
    a = static.sensed_along_axes(A_raw)
    if lever is None:
        return np.linalg.solve(static.C.T, a.T).T
    if w_dps is None:
        raise ValueError("lever-arm compensation needs the angular rate w_dps")
    w = np.broadcast_to(np.atleast_2d(w_dps), a.shape)
    dw = None if dwdt_dps2 is None else np.broadcast_to(np.atleast_2d(dwdt_dps2), a.shape)
    W = lever_matrix(w, dw) * (1e-3 / static.g_local)
    r = lever.r_for_compensation
    if lever.projection == "body_axis":
        return np.linalg.solve(static.C.T, a.T).T - np.einsum("nik,ik->ni", W, r)
    a = a - np.einsum("ji,njk,ik->ni", static.C, W, r)
    return np.linalg.solve(static.C.T, a.T).T


# How the reports show this model (calib_core.models.display).
register_display(
    ModelDisplay(
        "lever_arm",
        "Accelerometer lever arms (zhang2017 dynamic)",
        tuple(f"r{i}{a}" for i in (1, 2, 3) for a in "xyz"),
        rank=3,
        key_title="Accelerometer lever arms (zhang2017 dynamic)",
        symbols={f"r{i}{a}": ("r", f"{i}{a}") for i in (1, 2, 3) for a in "xyz"},
    )
)
