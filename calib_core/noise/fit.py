"""The composite noise model fitted to the whole Allan variance curve.

The model Allan variance is a sum of the processes' theoretical Allan variances
(:mod:`calib_core.noise.processes`), linear in the squared coefficients c_j, plus the fixed
contribution of periodic lines found in the spectrum. The squared coefficients are found by
non-negative weighted least squares over every cluster size, each Allan variance estimate
weighted by the inverse of its variance 2 sigma^4 / edf, with sigma^2 the model's own value
(iteratively reweighted: weighting by the measured value would pull the fit low). No line is
drawn on a slope: slope reading is biased (Guerrier, Molinari & Stebler, IEEE SPL 2016).

A squared coefficient's interval takes it as a scaled chi-square with 2 c^2 / var(c) degrees
of freedom, var(c) from the weighted least-squares covariance; a process fitted at zero gets
the interval c +- z var(c)^1/2 cut at zero when c is within z standard errors of zero.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy import optimize, stats

from calib_core.noise import processes
from calib_core.noise.allan import AllanCurve

COEFFICIENT_CONFIDENCE = 0.95
REWEIGHT_ITERATIONS = 6


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

    @property
    def p_value(self) -> float:
        return float(stats.chi2.sf(self.chi2, max(self.dof, 1)))

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


def coefficient_interval(c: float, se: float, level: float = COEFFICIENT_CONFIDENCE) -> tuple[float, float]:
    """Interval of sqrt(c) for a squared coefficient c with standard error se."""
    if not np.isfinite(se) or se <= 0:
        v = float(np.sqrt(max(c, 0.0)))
        return v, v
    z = stats.norm.ppf((1.0 + level) / 2.0)
    if c <= z * se:  # not distinguishable from zero: a two-sided normal interval cut at zero
        return float(np.sqrt(max(c - z * se, 0.0))), float(np.sqrt(c + z * se))
    nu = 2.0 * c * c / (se * se)
    lo = c * nu / stats.chi2.ppf((1.0 + level) / 2.0, nu)
    hi = c * nu / stats.chi2.ppf((1.0 - level) / 2.0, nu)
    return float(np.sqrt(lo)), float(np.sqrt(hi))


def _design(terms, tau, rate_hz):
    return np.column_stack([t.basis(tau, rate_hz) for t in terms]) if terms else np.zeros((tau.size, 0))


def _nnls_weighted(X, y, w):
    sw = np.sqrt(w)
    scale = np.linalg.norm(X * sw[:, None], axis=0)
    scale[scale == 0] = 1.0
    c, _ = optimize.nnls((X * sw[:, None]) / scale, y * sw)
    return c / scale


def weighted_chi2(avar: np.ndarray, model: np.ndarray, edf: np.ndarray) -> float:
    """sum edf (avar - model)^2 / (2 model^2): the misfit in units of each estimate's variance."""
    model = np.maximum(model, 1e-300)
    return float(np.sum(edf * (avar - model) ** 2 / (2.0 * model**2)))


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
    for _ in range(REWEIGHT_ITERATIONS):
        w = edf / (2.0 * model**2)
        c = _nnls_weighted(X, y, w)
        new = np.maximum(X @ c + fixed, 1e-300)
        if np.allclose(new, model, rtol=1e-6):
            model = new
            break
        model = new
    w = edf / (2.0 * model**2)
    c_se = np.full(c.size, np.nan)
    if c.size:
        info = (X * w[:, None]).T @ X
        scale = np.sqrt(np.diag(info))
        scale[scale == 0] = 1.0
        cov = np.linalg.pinv(info / np.outer(scale, scale)) / np.outer(scale, scale)
        c_se = np.sqrt(np.maximum(np.diag(cov), 0.0))
    adev_model = np.sqrt(model)
    within = float(np.mean((adev_model >= curve.adev_lo) & (adev_model <= curve.adev_hi)))
    active = int(np.sum(c > 0))
    return AllanFit(
        tuple(terms),
        c,
        c_se,
        model,
        weighted_chi2(avar, model, edf),
        int(tau.size - active),
        within,
        tuple(lines),
    )


def model_avar(fit: AllanFit, tau: np.ndarray, rate_hz: float) -> np.ndarray:
    """The fitted model's Allan variance at other cluster sizes (e.g. the other half's)."""
    X = _design(fit.terms, tau, rate_hz)
    out = X @ fit.c if fit.c.size else np.zeros_like(tau)
    for line in fit.lines:
        out = out + line.avar(tau, rate_hz)
    return out
