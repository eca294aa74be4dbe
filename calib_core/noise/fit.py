"""The composite noise model fitted to the whole Allan variance curve.

The model Allan variance is a sum of the processes' theoretical Allan variances
(:mod:`calib_core.noise.processes`), linear in the squared coefficients c_j, plus the fixed
contribution of periodic lines found in the spectrum. The squared coefficients are found by
non-negative generalized least squares over every cluster size: each Allan variance estimate
has the variance 2 sigma^4 / edf, sigma^2 the model's own value (iteratively reweighted:
weighting by the measured value would pull the fit low), and estimates at neighbouring
cluster sizes, made of the same data, are correlated (:data:`OCTAVE_CORRELATION`). No line is
drawn on a slope: slope reading is biased (Guerrier, Molinari & Stebler, IEEE SPL 2016).

A squared coefficient's interval takes it as a scaled chi-square with 2 c^2 / var(c) degrees
of freedom, var(c) from the generalized least-squares covariance; a process fitted at zero gets
the interval c +- z var(c)^1/2 cut at zero when c is within z standard errors of zero.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from functools import lru_cache

import numpy as np
from scipy import optimize, special, stats

from calib_core.linalg import nnls_stack
from calib_core.noise import processes
from calib_core.noise.allan import AllanCurve, chi2_ppf

COEFFICIENT_CONFIDENCE = 0.95
REWEIGHT_ITERATIONS = 6
# Correlation of overlapping Allan variance estimates one octave apart (made of the same
# data), by noise type: measured on 150 simulated records of each pure process here
# (quantization 0.15, white 0.5, flicker 0.68, random walk 0.88). Where processes mix, a
# cluster size takes the average over the model's processes weighted by their share of its
# Allan variance; estimates further apart are correlated by the product of the steps
# between them (a Markov chain over cluster sizes).
OCTAVE_CORRELATION = {2: 0.2, 1: 0.35, 0: 0.5, -1: 0.68, -2: 0.88}
PROCESS_ALPHA = {
    "quantization": 2,
    "white": 0,
    "bias_instability": -1,
    "random_walk": -2,
    "ramp": -2,
    "gauss_markov": -2,
}


@dataclass(frozen=True)
class Term:
    """One process of the composite model: ``name`` and, for a Gauss-Markov process, its
    correlation time."""

    name: str
    correlation_time_s: float | None = None

    def basis(self, tau: np.ndarray, rate_hz: float) -> np.ndarray:
        return processes.basis(self.name, tau, rate_hz, self.correlation_time_s)


@dataclass(frozen=True)
class Line:
    """A periodic line: frequency [Hz] and amplitude (channel unit, of A sin(2 pi f t))."""

    frequency_hz: float
    amplitude: float

    def avar(self, tau: np.ndarray, rate_hz: float) -> np.ndarray:
        return self.amplitude**2 * processes.periodic(tau, self.frequency_hz, rate_hz)


@dataclass(frozen=True)
class AllanFit:
    """Result of :func:`fit_allan`: squared coefficients ``c`` per term (channel unit and
    seconds), their standard errors, the model curve and its goodness of fit."""

    terms: tuple[Term, ...]
    c: np.ndarray
    c_se: np.ndarray
    model_avar: np.ndarray
    chi2: float
    dof: int
    fraction_within_ci: float
    lines: tuple[Line, ...] = field(default=())
    correlation: np.ndarray | None = None  # one-octave correlation used at each cluster size

    @property
    def p_value(self) -> float:
        return float(special.chdtrc(max(self.dof, 1), self.chi2))  # stats.chi2.sf's formula

    def coefficient(self, name: str) -> float | None:
        for t, c in zip(self.terms, self.c):
            if t.name == name:
                return float(np.sqrt(max(c, 0.0)))
        return None

    def interval(self, name: str, level: float = COEFFICIENT_CONFIDENCE) -> tuple[float, float] | None:
        """Interval of the coefficient (not squared); (0, upper bound) when fitted at zero."""
        for t, c, se in zip(self.terms, self.c, self.c_se):
            if t.name == name:
                return coefficient_interval(float(c), float(se), level)
        return None

    def goodness(self) -> dict:
        return {
            "chi2": self.chi2,
            "dof": self.dof,
            "p_value": self.p_value,
            "fraction_within_ci": self.fraction_within_ci,
        }


@lru_cache(maxsize=8)
def _normal_quantile(q: float) -> float:
    return float(stats.norm.ppf(q))


def coefficient_interval(c: float, se: float, level: float = COEFFICIENT_CONFIDENCE) -> tuple[float, float]:
    """Interval of sqrt(c) for a squared coefficient c with standard error se."""
    lo, hi = coefficient_intervals(np.array([c], float), np.array([se], float), level)
    return float(lo[0]), float(hi[0])


def coefficient_intervals(
    c: np.ndarray, se: np.ndarray, level: float = COEFFICIENT_CONFIDENCE
) -> tuple[np.ndarray, np.ndarray]:
    """Intervals (lo, hi) of sqrt(c) for squared coefficients c with standard errors se
    (arrays of one shape): c as a scaled chi-square with 2 c^2 / se^2 degrees of freedom;
    within z standard errors of zero, c +- z se cut at zero; sqrt(c) itself without a
    standard error."""
    c, se = np.asarray(c, float), np.asarray(se, float)
    z = _normal_quantile((1.0 + level) / 2.0)
    lo = np.sqrt(np.maximum(c, 0.0))
    hi = lo.copy()
    known = np.isfinite(se) & (se > 0)
    zse = z * np.where(known, se, 0.0)
    near = known & (c <= zse)  # not distinguishable from zero: a normal interval cut at zero
    if near.any():
        lo[near] = np.sqrt(np.maximum(c[near] - zse[near], 0.0))
        hi[near] = np.sqrt(c[near] + zse[near])
    far = known & ~near
    if far.any():
        cf, sf = c[far], se[far]
        nu = 2.0 * cf * cf / (sf * sf)
        lo[far] = np.sqrt(cf * nu / chi2_ppf((1.0 + level) / 2.0, nu))
        hi[far] = np.sqrt(cf * nu / chi2_ppf((1.0 - level) / 2.0, nu))
    return lo, hi


def _design(terms, tau, rate_hz):
    return np.column_stack([t.basis(tau, rate_hz) for t in terms]) if terms else np.zeros((tau.size, 0))


def _whitener(model: np.ndarray, edf: np.ndarray, r: np.ndarray) -> np.ndarray:
    """W with W^T W = Sigma^-1 for the Allan variance estimates' covariance Sigma: variances
    2 model^2 / edf; correlation between cluster sizes i < j the product of the octave steps
    s_k = sqrt(r_k r_(k+1)) between them (r: the one-octave correlation at each cluster
    size). That correlation is a Markov chain's, so W is bidiagonal: e_0 = z_0, e_k =
    (z_k - s_(k-1) z_(k-1)) / sqrt(1 - s_(k-1)^2) with z the standardized estimates. For
    (..., n) arguments, a stack (..., n, n)."""
    inv_sd = 1.0 / (np.sqrt(2.0 / edf) * np.maximum(model, 1e-300))
    step = np.sqrt(r[..., :-1] * r[..., 1:])
    norm = 1.0 / np.sqrt(1.0 - step**2)
    n = inv_sd.shape[-1]
    W = np.zeros(inv_sd.shape + (n,))
    W[..., 0, 0] = inv_sd[..., 0]
    k = np.arange(1, n)
    W[..., k, k] = norm * inv_sd[..., 1:]
    W[..., k, k - 1] = -norm * step * inv_sd[..., :-1]
    return W


def octave_correlation(alpha: np.ndarray) -> np.ndarray:
    """One-octave correlation at each cluster size from the identified noise types."""
    return np.array([OCTAVE_CORRELATION.get(int(a), 0.5) for a in alpha])


def _model_correlation(X: np.ndarray, c: np.ndarray, terms, fixed: np.ndarray, fallback: np.ndarray):
    """One-octave correlation at each cluster size from the model's mix of processes (lines
    count as white). ``c`` (p,) or a stack (B, p), ``fallback`` alike (n,) or (B, n)."""
    parts = X * c[..., None, :]
    total = parts.sum(axis=-1) + fixed
    r_terms = np.array([OCTAVE_CORRELATION[PROCESS_ALPHA[t.name]] for t in terms])
    with np.errstate(invalid="ignore", divide="ignore"):
        r = (parts @ r_terms + fixed * OCTAVE_CORRELATION[0]) / total
    return np.where(total > 0, r, fallback)


def _nnls_whitened(X: np.ndarray, y: np.ndarray, W: np.ndarray) -> np.ndarray:
    A = W @ X
    scale = np.linalg.norm(A, axis=0)
    scale[scale == 0] = 1.0
    c, _ = optimize.nnls(A / scale, W @ y)
    return c / scale


def weighted_chi2(avar: np.ndarray, model: np.ndarray, edf: np.ndarray, r: np.ndarray) -> float:
    """Generalized chi-square of the Allan variance estimates about the model: e^T Sigma^-1 e
    with the covariance of :func:`_whitener` (``r``: one-octave correlations)."""
    e = _whitener(model, edf, r) @ (avar - model)
    return float(e @ e)


def fit_allan(curve: AllanCurve, terms: tuple[Term, ...], lines: tuple[Line, ...] = ()) -> AllanFit:
    """Fit the squared coefficients of ``terms`` to the whole Allan variance curve, the
    lines' Allan variance held fixed."""
    tau, avar, edf = curve.tau_s, curve.avar, curve.edf
    X = _design(terms, tau, curve.rate_hz)
    fixed = np.zeros_like(tau)
    for line in lines:
        fixed += line.avar(tau, curve.rate_hz)
    y = avar - fixed
    model = np.maximum(avar, 1e-300)
    c = np.zeros(X.shape[1])
    r_id = octave_correlation(curve.alpha)
    r = r_id
    for _ in range(REWEIGHT_ITERATIONS):
        c = _nnls_whitened(X, y, _whitener(model, edf, r))
        new = np.maximum(X @ c + fixed, 1e-300)
        r = _model_correlation(X, c, terms, fixed, r_id)
        converged = bool(np.all(np.abs(new - model) <= 1e-4 * model))
        model = new
        if converged:
            break
    W = _whitener(model, edf, r)
    c_se = np.full(c.size, np.nan)
    if c.size:
        A = W @ X
        info = A.T @ A
        scale = np.sqrt(np.diag(info))
        scale[scale == 0] = 1.0
        cov = np.linalg.pinv(info / np.outer(scale, scale)) / np.outer(scale, scale)
        c_se = np.sqrt(np.maximum(np.diag(cov), 0.0))
    adev_model = np.sqrt(model)
    within = float(np.mean((adev_model >= curve.adev_lo) & (adev_model <= curve.adev_hi)))
    active = int(np.sum(c > 0))
    e = W @ (avar - model)
    return AllanFit(
        tuple(terms),
        c,
        c_se,
        model,
        float(e @ e),
        int(tau.size - active),
        within,
        tuple(lines),
        r,
    )


def fit_allan_stack(curves: list[AllanCurve], terms: tuple[Term, ...]) -> list[AllanFit]:
    """:func:`fit_allan` (no lines) of several curves at the same cluster sizes and rate (a
    record's channels), vectorised over the curves: the same iteratively reweighted
    non-negative generalized least squares, each curve iterated until its own convergence,
    its NNLS by :func:`calib_core.linalg.nnls_stack`. The figures are fit_allan's up to
    rounding."""
    tau, rate = curves[0].tau_s, curves[0].rate_hz
    avar = np.array([c.avar for c in curves])
    edf = np.array([c.edf for c in curves])
    X = _design(terms, tau, rate)
    model = np.maximum(avar, 1e-300)
    c = np.zeros((len(curves), X.shape[1]))
    r_id = np.array([octave_correlation(cv.alpha) for cv in curves])
    r = r_id.copy()
    active = np.ones(len(curves), bool)
    for _ in range(REWEIGHT_ITERATIONS):
        W = _whitener(model, edf, r)
        A = W @ X
        scale = np.sqrt(np.add.reduce(A * A, axis=-2))  # np.linalg.norm's own sum
        scale[scale == 0] = 1.0
        y_w = np.einsum("bij,bj->bi", W, avar)
        c_new = nnls_stack(A / scale[:, None, :], y_w) / scale
        new = np.maximum(c_new @ X.T, 1e-300)
        r_new = _model_correlation(X, c_new, terms, 0.0, r_id)
        converged = np.all(np.abs(new - model) <= 1e-4 * model, axis=-1)
        c[active], r[active], model[active] = c_new[active], r_new[active], new[active]
        active &= ~converged
        if not active.any():
            break
    W = _whitener(model, edf, r)
    A = W @ X
    info = np.swapaxes(A, -1, -2) @ A
    scale = np.sqrt(np.diagonal(info, axis1=-2, axis2=-1))
    scale = np.where(scale == 0, 1.0, scale)
    outer = scale[:, :, None] * scale[:, None, :]
    cov = np.linalg.pinv(info / outer) / outer
    c_se = np.sqrt(np.maximum(np.diagonal(cov, axis1=-2, axis2=-1), 0.0))
    adev_model = np.sqrt(model)
    e = np.einsum("bij,bj->bi", W, avar - model)
    lo, hi = np.array([cv.adev_lo for cv in curves]), np.array([cv.adev_hi for cv in curves])
    within = np.mean((adev_model >= lo) & (adev_model <= hi), axis=1).tolist()
    dof = (tau.size - np.sum(c > 0, axis=1)).tolist()
    return [
        AllanFit(tuple(terms), c[i], c_se[i], model[i], float(e[i] @ e[i]), dof[i], within[i], (), r[i])
        for i in range(len(curves))
    ]


def model_avar(fit: AllanFit, tau: np.ndarray, rate_hz: float) -> np.ndarray:
    """The fitted model's Allan variance at other cluster sizes (e.g. the other half's)."""
    X = _design(fit.terms, tau, rate_hz)
    out = X @ fit.c if fit.c.size else np.zeros_like(tau)
    for line in fit.lines:
        out = out + line.avar(tau, rate_hz)
    return out
