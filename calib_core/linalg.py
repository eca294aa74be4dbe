"""Least squares with standard errors, the one solver every estimator uses."""
from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

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
class _Factorisation:
    """What the solve needs of a design X alone (its arrays are shared: read-only)."""

    norms: np.ndarray
    U: np.ndarray
    s_inv: np.ndarray
    Vt: np.ndarray
    rank: int
    cond: float
    cov_unscaled: np.ndarray


def _factorise(X: np.ndarray, rcond: float) -> _Factorisation:
    norms = np.linalg.norm(X, axis=0)
    norms[norms == 0] = 1.0
    Xs = X / norms
    U, s, Vt = np.linalg.svd(Xs, full_matrices=False)
    rank = int((s > rcond * s[0]).sum()) if s.size and s[0] > 0 else 0
    cond = float(s[0] / s[-1]) if s.size and s[-1] > 0 else float("inf")
    s_inv = np.where(s > rcond * (s[0] if s.size else 0), 1.0 / np.where(s == 0, 1, s), 0.0)
    cov_s = (Vt.T * s_inv ** 2) @ Vt
    cov_unscaled = cov_s / np.outer(norms, norms)
    return _Factorisation(norms, U, s_inv, Vt, rank, cond, cov_unscaled)


@lru_cache(maxsize=32)
def _factorise_cached(shape: tuple[int, int], data: bytes, rcond: float) -> _Factorisation:
    fac = _factorise(np.frombuffer(data, dtype=float).reshape(shape).copy(), rcond)
    for a in (fac.norms, fac.U, fac.s_inv, fac.Vt, fac.cov_unscaled):
        a.setflags(write=False)
    return fac


def solve_lstsq(X: np.ndarray, Y: np.ndarray, rcond: float = 1e-10,
                reuse_design: bool = False) -> LstsqResult:
    """Least squares via SVD of the column-equilibrated design (never inv(X^T X)).

    Columns are scaled to unit norm first: the condition number then measures the geometry
    of the design, not the units of its columns, and the solve is better conditioned.

    ``reuse_design=True`` for a design that is the same for many calls (one built from a
    protocol's references, identical for every session of a fleet): its factorisation is
    kept in a small cache keyed by the design's bytes, so a fleet pays one SVD per design.
    The numbers are identical either way.
    """
    X = np.asarray(X, dtype=float)
    Y = np.asarray(Y, dtype=float)
    squeeze = Y.ndim == 1
    if squeeze:
        Y = Y[:, None]
    n, p = X.shape
    if reuse_design:
        X = np.ascontiguousarray(X)
        fac = _factorise_cached(X.shape, X.tobytes(), float(rcond))
    else:
        fac = _factorise(X, rcond)
    coef_s = fac.Vt.T @ (fac.s_inv[:, None] * (fac.U.T @ Y))
    coef = coef_s / fac.norms[:, None]
    resid = Y - X @ coef
    dof = n - fac.rank
    sigma2 = (resid ** 2).sum(axis=0) / dof if dof > 0 else np.full(Y.shape[1], np.nan)
    cov_unscaled = fac.cov_unscaled.copy()
    stderr = np.sqrt(np.outer(np.diag(cov_unscaled), sigma2))
    if squeeze:
        coef, resid, stderr = coef[:, 0], resid[:, 0], stderr[:, 0]
    return LstsqResult(coef, cov_unscaled, sigma2, stderr, resid, dof, fac.cond, fac.rank)
