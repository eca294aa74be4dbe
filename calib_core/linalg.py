"""Least squares with standard errors, the one solver every estimator uses."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class LstsqResult:
    """Solution of Y ~ X B for several right-hand sides sharing one design X.

    ``coef`` (p, k); ``cov_unscaled`` (X^T X)^-1 (p, p); ``sigma2`` (k,) residual variance per
    right-hand side; ``stderr`` (p, k); ``residuals`` (n, k); ``dof``; ``condition_number`` of
    the column-equilibrated design (so raw LSB or V columns do not inflate it); ``rank``.
    """

    coef: np.ndarray
    cov_unscaled: np.ndarray
    sigma2: np.ndarray
    stderr: np.ndarray
    residuals: np.ndarray
    dof: int
    condition_number: float
    rank: int


@dataclass(frozen=True)
class LstsqStack:
    """R least-squares problems of one shape solved together (the repetitions of a unit):
    every field of :class:`LstsqResult` with a leading axis of R (``dof``,
    ``condition_number`` and ``rank`` are (R,) arrays). Problem r's numbers are those
    :func:`solve_lstsq` gives for it alone, bit for bit: the stacked LAPACK and BLAS calls
    run the same routine on each problem."""

    coef: np.ndarray
    cov_unscaled: np.ndarray
    sigma2: np.ndarray
    stderr: np.ndarray
    residuals: np.ndarray
    dof: np.ndarray
    condition_number: np.ndarray
    rank: np.ndarray


@dataclass(frozen=True)
class _Factorisation:
    """What the solve needs of a design X alone; for a stack of designs (..., n, p) every
    field has the stack's leading axes."""

    norms: np.ndarray
    U: np.ndarray
    s_inv: np.ndarray
    Vt: np.ndarray
    rank: np.ndarray
    cond: np.ndarray
    cov_unscaled: np.ndarray


def _factorise(X: np.ndarray, rcond: float) -> _Factorisation:
    norms = np.linalg.norm(X, axis=-2)
    norms[norms == 0] = 1.0
    Xs = X / norms[..., None, :]
    U, s, Vt = np.linalg.svd(Xs, full_matrices=False)
    largest, smallest = s[..., :1], s[..., -1]
    kept = s > rcond * largest
    rank = kept.sum(axis=-1)  # 0 when the largest singular value is 0
    positive = smallest > 0
    cond = np.where(positive, s[..., 0] / np.where(positive, smallest, 1.0), np.inf)
    s_inv = np.where(kept, 1.0 / np.where(s == 0, 1, s), 0.0)
    cov_s = (np.swapaxes(Vt, -1, -2) * s_inv[..., None, :] ** 2) @ Vt
    cov_unscaled = cov_s / (norms[..., :, None] * norms[..., None, :])
    return _Factorisation(norms, U, s_inv, Vt, rank, cond, cov_unscaled)


def solve_lstsq(X: np.ndarray, Y: np.ndarray, rcond: float = 1e-10) -> LstsqResult:
    """Least squares via SVD of the column-equilibrated design (never inv(X^T X)).

    Columns are scaled to unit norm first: the condition number then measures the geometry
    of the design, not the units of its columns, and the solve is better conditioned.
    """
    X = np.asarray(X, dtype=float)
    Y = np.asarray(Y, dtype=float)
    squeeze = Y.ndim == 1
    ls = solve_lstsq_stack(X[None], (Y[:, None] if squeeze else Y)[None], rcond)
    coef, resid, stderr = ls.coef[0], ls.residuals[0], ls.stderr[0]
    if squeeze:
        coef, resid, stderr = coef[:, 0], resid[:, 0], stderr[:, 0]
    return LstsqResult(
        coef,
        ls.cov_unscaled[0],
        ls.sigma2[0],
        stderr,
        resid,
        int(ls.dof[0]),
        float(ls.condition_number[0]),
        int(ls.rank[0]),
    )


def solve_lstsq_stack(X: np.ndarray, Y: np.ndarray, rcond: float = 1e-10) -> LstsqStack:
    """:func:`solve_lstsq` of R problems at once: X (R, n, p), or (n, p) when the design is
    the same for all; Y (R, n, k), or (n, k) when the right-hand sides are. One stacked SVD
    and one matmul per step instead of R of each (problem r's numbers are those of
    ``solve_lstsq(X[r], Y[r])``; a shared 2-D X is factorised once)."""
    X = np.asarray(X, dtype=float)
    Y = np.asarray(Y, dtype=float)
    fac = _factorise(X, rcond)
    coef_s = np.swapaxes(fac.Vt, -1, -2) @ (fac.s_inv[..., :, None] * (np.swapaxes(fac.U, -1, -2) @ Y))
    coef = coef_s / fac.norms[..., :, None]
    resid = Y - X @ coef
    n_problems = coef.shape[0]
    stacked = X.ndim == 3  # a design per problem: the factorisation's arrays are the problems'
    dof = X.shape[-2] - fac.rank
    if not stacked:
        dof = np.broadcast_to(dof, (n_problems,))
    sum_sq = (resid**2).sum(axis=-2)
    if (dof > 0).all():
        sigma2 = sum_sq / dof[:, None]
    else:
        sigma2 = np.full(sum_sq.shape, np.nan)
        np.divide(sum_sq, dof[:, None], out=sigma2, where=dof[:, None] > 0)
    cov_unscaled = (
        fac.cov_unscaled
        if stacked
        else np.broadcast_to(fac.cov_unscaled, (n_problems,) + fac.cov_unscaled.shape[-2:]).copy()
    )
    variance = np.diagonal(cov_unscaled, axis1=-2, axis2=-1)
    stderr = np.sqrt(variance[:, :, None] * sigma2[:, None, :])
    return LstsqStack(
        coef,
        cov_unscaled,
        sigma2,
        stderr,
        resid,
        dof,
        fac.cond if stacked else np.broadcast_to(fac.cond, (n_problems,)),
        fac.rank if stacked else np.broadcast_to(fac.rank, (n_problems,)),
    )


# -- small pseudo-inverse solves (model discovery's joint fit) --------------------------------------
# Discovery solves many small problems on R factors (k x k, k ~ 10-40) whose columns may be
# exactly 0 or not determined by the steps: the pseudo-inverse on the determined directions,
# with the covariance built only when a caller asks for it.
PINV_RCOND = 1e-10


@dataclass
class PinvSolution:
    """What :func:`lstsq_pinv` keeps of its SVD for the covariance of the solution."""

    Vt: np.ndarray
    inv_s: np.ndarray
    keep: np.ndarray
    live: np.ndarray
    scale: np.ndarray
    s: np.ndarray | None = None  # the scaled design's singular values
    U: np.ndarray | None = None  # its left singular vectors (kept by pinv_solutions)

    @property
    def cov_pinv(self) -> np.ndarray:
        """(Z^T Z)^+ in the columns' own units, the pseudo-inverse on the determined
        directions and nothing marked."""
        return (self.Vt.T * self.inv_s**2) @ self.Vt / np.outer(self.scale, self.scale)

    @property
    def cov(self) -> np.ndarray:
        """(Z^T Z)^+ in the columns' own units; a parameter with a component along an
        undetermined direction, or whose column is 0, is NaN (built once, on first use)."""
        if "_cov" not in self.__dict__:
            Vt, inv_s, keep, live, scale = self.Vt, self.inv_s, self.keep, self.live, self.scale
            cov = (Vt.T * inv_s**2) @ Vt / np.outer(scale, scale)
            undetermined = (np.abs(Vt[~keep]) > 1e-6).any(axis=0) | ~live
            cov[undetermined, :] = np.nan
            cov[:, undetermined] = np.nan
            self.__dict__["_cov"] = cov
        return self.__dict__["_cov"]


def lstsq_pinv(
    Z: np.ndarray, y: np.ndarray, rcond: float | None = None, live_rtol: float = 1e-12
) -> tuple[np.ndarray, int, PinvSolution]:
    """Least squares with column scaling, the pseudo-inverse on directions the data do not
    determine (singular values below ``rcond`` of the largest; default sqrt(PINV_RCOND)):
    theta, rank, and the SVD's parts for the covariance. A column whose norm is at most
    ``live_rtol`` of the largest is not scaled and gets no estimate (theta 0); with
    ``live_rtol`` 0, only an all-zero column is left unscaled and its theta is what the
    pseudo-inverse gives."""
    live, scale = _pinv_scale(Z, live_rtol)
    U, s, Vt = np.linalg.svd(Z / scale, full_matrices=False)
    solution = _pinv_solution(s, Vt, live, scale, rcond)
    rank = int(solution.keep.sum())
    theta = (Vt.T * solution.inv_s) @ (U.T @ y) / scale
    if live_rtol:
        theta[~live] = 0.0
    return theta, rank, solution


def pinv_theta(solution: PinvSolution, y: np.ndarray) -> tuple[np.ndarray, int]:
    """theta and rank of :func:`lstsq_pinv` (default rcond and live_rtol) of the design a
    :func:`pinv_solutions` solution is of, for the right-hand side ``y``: its SVD not
    computed again (the same numbers)."""
    theta = (solution.Vt.T * solution.inv_s) @ (solution.U.T @ y) / solution.scale
    theta[~solution.live] = 0.0
    return theta, int(solution.keep.sum())


def pinv_solutions(Zs: list[np.ndarray]) -> list[PinvSolution]:
    """The :class:`PinvSolution` of :func:`lstsq_pinv` (default rcond and live_rtol) of each
    design, for their covariances: one batched SVD per distinct shape (the same numbers as
    one call each)."""
    scaled = [_pinv_scale(Z, 1e-12) for Z in Zs]
    by_shape: dict[tuple[int, ...], list[int]] = {}
    for i, Z in enumerate(Zs):
        by_shape.setdefault(Z.shape, []).append(i)
    out: list[PinvSolution | None] = [None] * len(Zs)
    for group in by_shape.values():
        U, s, Vt = np.linalg.svd(np.array([Zs[i] / scaled[i][1] for i in group]), full_matrices=False)
        for j, i in enumerate(group):
            out[i] = _pinv_solution(s[j], Vt[j], *scaled[i], None)
            out[i].U = U[j]
    return out


def _pinv_scale(Z: np.ndarray, live_rtol: float) -> tuple[np.ndarray, np.ndarray]:
    """Which columns of Z are live and the scale each is divided by (:func:`lstsq_pinv`)."""
    norms = np.sqrt(np.add.reduce(Z * Z, axis=0))  # np.linalg.norm(Z, axis=0), its arithmetic
    live = norms > live_rtol * max(norms.max(), 1e-300) if live_rtol else norms > 0
    return live, np.where(live, norms, 1.0)


def _pinv_solution(
    s: np.ndarray, Vt: np.ndarray, live: np.ndarray, scale: np.ndarray, rcond: float | None
) -> PinvSolution:
    """The pseudo-inverse's parts from the SVD of the scaled design (:func:`lstsq_pinv`)."""
    r = PINV_RCOND**0.5 if rcond is None else rcond
    keep = s > r * s[0] if len(s) and s[0] > 0 else np.zeros(len(s), bool)
    keep &= s > 0
    inv_s = np.where(keep, 1.0 / np.where(keep, s, 1.0), 0.0)
    return PinvSolution(Vt, inv_s, keep, live, scale, s)


def lstsq_min_norm(
    Z: np.ndarray, y: np.ndarray, svd: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None
) -> tuple[np.ndarray, int, np.ndarray]:
    """Minimum-norm least squares by one SVD, with numpy's rank rule (singular values above
    max(m, p) eps of the largest, as ``np.linalg.lstsq(rcond=None)`` and ``matrix_rank``):
    theta (p,) or (p, q) for y (m,) or (m, q), the rank, and the fitted values Z theta (the
    projection of y on the columns' span). ``svd``: ``np.linalg.svd(Z, full_matrices=False)``
    when the caller has it."""
    U, s, Vt = np.linalg.svd(Z, full_matrices=False) if svd is None else svd
    keep = s > (s[0] if len(s) else 0.0) * max(Z.shape) * np.finfo(float).eps
    Uk = U[:, keep]
    uy = Uk.T @ y
    theta = Vt[keep].T @ (uy / (s[keep] if uy.ndim == 1 else s[keep, None]))
    return theta, int(keep.sum()), Uk @ uy


def lstsq_pinv_cov(Z: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray, int]:
    """:func:`lstsq_pinv` with its covariance: theta, (Z^T Z)^+ (NaN where undetermined), rank."""
    theta, rank, solution = lstsq_pinv(Z, y)
    return theta, solution.cov, rank


def lstsq_pinv_stack(Z: np.ndarray, y: np.ndarray) -> np.ndarray:
    """theta of :func:`lstsq_pinv` for a stack of problems, Z (B, m, p), y (B, m): one batched
    SVD."""
    norms = np.linalg.norm(Z, axis=-2)  # (B, p)
    live = norms > 1e-12 * np.maximum(norms.max(axis=-1, keepdims=True), 1e-300)
    scale = np.where(live, norms, 1.0)
    U, s, Vt = np.linalg.svd(Z / scale[:, None, :], full_matrices=False)
    keep = (s > PINV_RCOND**0.5 * s[:, :1]) & (s[:, :1] > 0) & (s > 0)
    inv_s = np.where(keep, 1.0 / np.where(keep, s, 1.0), 0.0)
    uy = np.einsum("bmk,bm->bk", U, y)
    theta = np.einsum("bkp,bk->bp", Vt, inv_s * uy) / scale
    return np.where(live, theta, 0.0)


def nnls_stack(A: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Non-negative least squares, min ||A x - b|| subject to x >= 0, of a stack of small
    problems, A (B, m, p), b (B, m), p a few columns: x (B, p). A problem whose least
    squares (:func:`lstsq_pinv_stack`) is non-negative has it as its answer; for the others
    each column subset's least squares is tried and the answer is the feasible one (every
    coefficient >= 0, x = 0 included) of smallest residual, which is the problem's minimum
    when A has full column rank (the optimum is the least squares of its positive
    coefficients' columns). Up to 2^p - 1 batched solves: for p up to ~4."""
    B, _, p = A.shape
    x = lstsq_pinv_stack(A, b)
    todo = np.flatnonzero(~np.all(x >= 0, axis=1))
    if not len(todo):
        return x
    A, b = A[todo], b[todo]
    best = np.zeros((len(todo), p))
    best_ss = np.einsum("bm,bm->b", b, b)
    # every one-column subset at once: its projection, without an SVD (each column's
    # values contiguous, as one column's alone)
    by_col = np.ascontiguousarray(A.transpose(0, 2, 1))  # (B, p, m)
    aa = np.einsum("bkm,bkm->bk", by_col, by_col)
    ab = np.einsum("bkm,bm->bk", by_col, b)
    one = np.where(aa > 0, ab / np.where(aa > 0, aa, 1.0), 0.0)
    r_one = by_col * one[:, :, None] - b[:, None, :]
    ss_one = np.einsum("bkm,bkm->bk", r_one, r_one)
    for mask in range(1, (1 << p) - 1):
        cols = [j for j in range(p) if mask >> j & 1]
        if len(cols) == 1:
            xs, ss = one[:, cols], ss_one[:, cols[0]]
        else:
            sub = A[:, :, cols]
            xs = lstsq_pinv_stack(sub, b)
            r = np.einsum("bmk,bk->bm", sub, xs) - b
            ss = np.einsum("bm,bm->b", r, r)
        better = (xs >= 0).all(axis=1) & (ss < best_ss)
        if better.any():
            x_mask = np.zeros_like(best)
            x_mask[:, cols] = xs
            best[better] = x_mask[better]
            best_ss = np.where(better, ss, best_ss)
    x[todo] = best
    return x


def qr_r(X: np.ndarray) -> np.ndarray:
    """R factor of each matrix of a stack (..., m, k), padded with zero rows to (..., k, k)."""
    Rf = np.linalg.qr(X, mode="r")
    k = X.shape[-1]
    if Rf.shape[-2] < k:
        pad = np.zeros(Rf.shape[:-2] + (k - Rf.shape[-2], k))
        Rf = np.concatenate([Rf, pad], axis=-2)
    return Rf


def qr_r_columns(X: np.ndarray, columns: list[list[int]]) -> np.ndarray:
    """:func:`qr_r` of each block X[c] (c along the first axis; each block a stack
    (..., m, k)) whose columns outside ``columns[c]`` (increasing) are 0: factorised on
    those columns alone, consecutive blocks with the same columns in one call. R[c]
    (..., k, k) is upper triangular, its rows from len(columns[c]) on 0, its columns outside
    0; R^T R = X^T X. Blocks with every column are factorised as by :func:`qr_r` (the same
    numbers)."""
    k = X.shape[-1]
    out = np.zeros(X.shape[:-2] + (k, k))
    start = 0
    while start < len(columns):
        cols = columns[start]
        end = start + 1
        while end < len(columns) and columns[end] == cols:
            end += 1
        if len(cols) == k:
            out[start:end] = qr_r(X[start:end])
        else:
            out[start:end, ..., : len(cols), cols] = qr_r(X[start:end][..., cols])
        start = end
    return out


# -- normal equations of small, well-posed weighted fits (the step consistency check) ----------
# Below this determinant of the diagonally equilibrated normal matrix (unit diagonal, so
# its determinant is at most 1) a problem is solved by the pseudo-inverse instead: the
# smallest eigenvalue is at least det / p**(p - 1) and the largest at most p, so the LU
# solve only meets matrices of condition below p**p / det (~5e6 for p = 6), whose rounding
# (~condition x 1e-16) stays below the 1e-8 relative the consistency check's residuals are
# held to.
NORMAL_MIN_DET = 1e-2


def solve_normal_stack(A: np.ndarray, b: np.ndarray, pseudo_inverse: bool | np.ndarray = False) -> np.ndarray:
    """x of ``A x = b`` for a stack of normal matrices A (..., p, p) (symmetric, positive
    semi-definite: X^T W X) and right-hand sides b (..., p, k) with the same leading axes:
    ``np.linalg.pinv(A) @ b`` (the minimum-norm solution) to rounding, without an SVD of
    each matrix. Each A is scaled to a unit diagonal and solved by LU; a zero column of X (a
    zero row and column of A) gets a zero coefficient, as from the pseudo-inverse; a problem
    whose scaled matrix is near singular (determinant below ``NORMAL_MIN_DET``) takes the
    pseudo-inverse. ``pseudo_inverse`` (True, or a mask of the leading axes): the problems
    solved by ``np.linalg.pinv(A) @ b`` itself (its rounding, problem by problem)."""
    if pseudo_inverse is True:
        return np.linalg.pinv(A) @ b
    diag = np.diagonal(A, axis1=-2, axis2=-1)
    zero = diag <= 0
    scale = 1.0 / np.sqrt(np.where(zero, 1.0, diag))
    As = A * scale[..., :, None] * scale[..., None, :]
    if zero.any():
        As = As + zero[..., None] * np.eye(A.shape[-1])  # zero row and column: 1 on the diagonal
    bs = b * scale[..., :, None]
    hard = ~(np.linalg.det(As) >= NORMAL_MIN_DET)  # NaN included
    if pseudo_inverse is not False:
        hard |= pseudo_inverse
    if not hard.any():
        return np.linalg.solve(As, bs) * scale[..., :, None]
    # every matrix is solved on its own: the hard ones solve the identity in the stack
    # (their LU would fail), then take the pseudo-inverse
    As[hard] = np.eye(A.shape[-1])
    x = np.linalg.solve(As, bs) * scale[..., :, None]
    x[hard] = np.linalg.pinv(A[hard]) @ b[hard]
    return x
