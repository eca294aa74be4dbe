"""Overlapping Allan deviation at octave cluster sizes with Stable32-style confidence
intervals: the noise type at each cluster size identified by lag-1 autocorrelation (Riley &
Greenhall), the equivalent degrees of freedom by Greenhall's algorithm, the interval from the
chi-square distribution. allantools does each of these; this module only drives it and keeps
what the fit needs (the Allan variance and its edf per cluster size)."""

from __future__ import annotations

import warnings
from dataclasses import dataclass
from functools import lru_cache

import allantools
import numpy as np
from allantools import ci as allan_ci
from scipy import special
from threadpoolctl import threadpool_limits

ADEV_CONFIDENCE = 0.95  # two-sided level of adev_lo .. adev_hi
MIN_CLUSTERS = 8  # the largest cluster size leaves >= 8 cluster lengths in the record
MIN_NOISE_ID_POINTS = 32  # lag-1 autocorrelation noise ID needs ~30 averaged points
# ...and gains nothing past ~65,000 (lag-1 autocorrelation to +-0.004): longer records are
# identified on their first 65,536 averages, which keeps small cluster sizes cheap.
MAX_NOISE_ID_POINTS = 65_536


@dataclass(frozen=True)
class AllanCurve:
    """Overlapping Allan deviation of one channel. ``alpha`` is the identified power-law noise
    type per cluster size (rate data: 0 white, -1 flicker, -2 random walk, +2 quantization);
    ``edf`` the equivalent degrees of freedom behind ``adev_lo``/``adev_hi`` (level
    :data:`ADEV_CONFIDENCE`)."""

    tau_s: np.ndarray
    m: np.ndarray
    adev: np.ndarray
    adev_lo: np.ndarray
    adev_hi: np.ndarray
    edf: np.ndarray
    alpha: np.ndarray
    rate_hz: float
    n_samples: int

    @property
    def avar(self) -> np.ndarray:
        return self.adev**2

    def to_dict(self) -> dict:
        return {
            "tau_s": self.tau_s.tolist(),
            "adev": self.adev.tolist(),
            "adev_lo": self.adev_lo.tolist(),
            "adev_hi": self.adev_hi.tolist(),
            "edf": self.edf.tolist(),
            "noise_type_alpha": self.alpha.astype(int).tolist(),
            "confidence": ADEV_CONFIDENCE,
        }


def octave_cluster_sizes(n_samples: int) -> np.ndarray:
    """m = 1, 2, 4, ... while the record holds at least :data:`MIN_CLUSTERS` clusters."""
    top = max(1, n_samples // MIN_CLUSTERS)
    return 2 ** np.arange(int(np.floor(np.log2(top))) + 1)


def _lag1_acf(z: np.ndarray) -> float:
    """Riley (2004) eq. 2: allantools' ``lag1_acf``, vectorized (its loop is pure Python)."""
    d = z - _mean(z)
    den = float(d @ d)
    return float(d[:-1] @ d[1:]) / den if den > 0 else 0.0


@lru_cache(maxsize=64)
def _centred_index(k: int) -> tuple[np.ndarray, float]:
    """0 .. k-1 minus its mean (read-only), and its sum of squares."""
    t = np.arange(k, dtype=float)
    t -= t.mean()
    t.setflags(write=False)
    return t, float(t @ t)


def _mean(z: np.ndarray) -> float:
    """``z.mean()`` of a 1-d float array, the same figure without ``ndarray.mean``'s
    Python-level argument handling (a few microseconds a call, thousands of calls a fleet)."""
    return np.add.reduce(z) / z.size


def _detrend_linear(z: np.ndarray) -> np.ndarray:
    zc = z - _mean(z)
    if z.size <= 1:
        return zc
    t, tt = _centred_index(z.size)
    return zc - (float(t @ zc) / tt) * t


def identify_alpha(x: np.ndarray, m: int) -> int | None:
    """Power-law noise type of rate data x at cluster size m: the lag-1 autocorrelation noise
    ID of Riley & Greenhall as allantools' ``autocorr_noise_id`` (data_type="freq", dmax=2)
    does it, on the m-averages with a linear trend removed (at most
    :data:`MAX_NOISE_ID_POINTS` of them). None when fewer than :data:`MIN_NOISE_ID_POINTS`
    averages remain. Flicker PM (alpha = 1), which no process of
    the model makes, is read as white (alpha = 0, the smaller edf); the result is clipped to
    the range Greenhall's edf accepts for the Allan variance (alpha > -3)."""
    k = min(x.size // m, MAX_NOISE_ID_POINTS)
    if k < MIN_NOISE_ID_POINTS:
        return None
    return _alpha_of_averages(x[: k * m].reshape(k, m).mean(axis=1))


def _alpha_of_averages(z: np.ndarray) -> int:
    """:func:`identify_alpha`'s rule on the m-averages ``z`` (or the sums of m rates: the
    rule does not see a scale)."""
    r1 = _detrended_lag1_acf(z)
    d = 0
    while True:
        rho = r1 / (1.0 + r1)
        if rho < 0.25 or d >= 2:
            alpha = int(-1.0 * round(2 * rho) - 2.0 * d)  # half to even, as np.round
            break
        z = np.diff(_detrend_linear(z) if d == 0 else z)
        d += 1
        r1 = _lag1_acf(z)
    if alpha == 1:
        alpha = 0
    return min(max(alpha, -2), 2)


def _detrended_lag1_acf(z: np.ndarray) -> float:
    """``_lag1_acf(_detrend_linear(z))`` from z's sums (sum, sum of squares, lag-1 sum of
    products, sum against the centred index) without forming the detrended values: four
    passes over z instead of ten. The detrended values w = z - mean - b t (b = t.z / t.t)
    sum to zero, so w.w = z.z - S^2 / k - b t.z, and their lag-1 sum of products follows
    from the same sums and the ends z_0, z_(k-1) (t_(i+1) = t_i + 1). The same figure up to
    rounding; a series whose variance about its trend is under 1e-3 of its sum of squares
    (a large offset or trend, whose sums would cancel) takes the direct form."""
    k = z.size
    if k < 3:
        return _lag1_acf(_detrend_linear(z))
    z = np.ascontiguousarray(z)  # every m-th sum: the products below run by BLAS only on a copy
    t, tt = _centred_index(k)
    s, q = float(np.add.reduce(z)), float(z @ z)
    lag, tz = float(z[:-1] @ z[1:]), float(t @ z)
    mean, b, h = s / k, tz / tt, (k - 1) / 2.0
    den = q - s * mean - b * tz
    if not den > 1e-3 * q:
        return _lag1_acf(_detrend_linear(z))
    z0, z1 = float(z[0]), float(z[-1])
    num = (
        lag
        - mean * (2.0 * s - z0 - z1)
        - b * (2.0 * tz + (h + 1.0) * (z0 - z1))
        + (k - 1) * mean * mean
        + b * b * (tt - h * h - h)
    )
    return num / den


@lru_cache(maxsize=1024)
def equivalent_dof(alpha: int, m: int, n_samples: int) -> float:
    """Greenhall's edf of the overlapping Allan variance (N phase points = n + 1)."""
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            edf = float(allan_ci.edf_greenhall(alpha=alpha, d=2, m=int(m), N=n_samples + 1, overlapping=True))
    except (AssertionError, ValueError, ZeroDivisionError):
        edf = float("nan")
    if not np.isfinite(edf) or edf <= 0:
        edf = float(allan_ci.edf_simple(n_samples + 1, int(m), alpha))
    return max(edf, 1.0)


def chi2_ppf(q, df):
    """``scipy.stats.chi2.ppf(q, df)`` for 0 < q < 1 and df > 0, the same figures: the
    distribution's own formula without ``rv_continuous``'s argument checks (tens of
    microseconds a call, which the many small intervals of a fleet add up)."""
    return 2.0 * special.gammaincinv(np.asarray(df, float) / 2, q)


def chi2_interval(value: np.ndarray, edf: np.ndarray, level: float = ADEV_CONFIDENCE):
    """Interval of a deviation estimated with edf degrees of freedom (NIST SP 1065 eq. 45)."""
    lo_q = chi2_ppf((1.0 + level) / 2.0, edf)
    hi_q = chi2_ppf((1.0 - level) / 2.0, edf)
    return value * np.sqrt(edf / lo_q), value * np.sqrt(edf / hi_q)


def allan_curve(
    x: np.ndarray,
    rate_hz: float,
    m: np.ndarray | None = None,
    alpha: np.ndarray | None = None,
) -> AllanCurve:
    """Overlapping Allan deviation of rate samples ``x`` (any unit) at cluster sizes ``m``
    (default: octaves). ``alpha`` reuses noise types identified elsewhere (e.g. on the whole
    record for its halves); otherwise each cluster size's type is identified here, and where
    too few points remain the next redder type than the last identified one is taken (its
    edf is the smaller: the interval errs wide where the type cannot be told)."""
    x = np.asarray(x, float)
    n = x.size
    if m is None:
        m = octave_cluster_sizes(n)
    m = np.asarray(m, int)
    m = m[m <= max(1, n // MIN_CLUSTERS)]
    if m.size == 0 or n < 2 * MIN_CLUSTERS:
        raise ValueError(f"a record of {n} samples is too short for an Allan deviation")
    with threadpool_limits(1):  # see analysis.analyse_recording: one BLAS thread is faster here
        return _allan_curve(x, rate_hz, m, alpha)


def _allan_curve(x: np.ndarray, rate_hz: float, m: np.ndarray, alpha: np.ndarray | None) -> AllanCurve:
    n = x.size
    y = x - x.mean()
    taus, adev, _, _ = allantools.oadev(y, rate=rate_hz, data_type="freq", taus=m / rate_hz)
    keep = np.isin(np.rint(taus * rate_hz).astype(int), m)
    taus, adev = taus[keep], adev[keep]
    m = np.rint(taus * rate_hz).astype(int)
    if alpha is None:
        ids = []
        last, stepped = 0, False
        for mj in m:
            a = identify_alpha(y, int(mj))
            if a is not None:
                last = a
            elif not stepped:  # too few averages to tell: the next redder type, smaller edf
                last, stepped = max(last - 1, -2), True
            ids.append(last)
        alpha = np.array(ids, int)
    else:
        alpha = np.asarray(alpha, int)[: m.size]
    edf = np.array([equivalent_dof(int(a), int(mj), n) for a, mj in zip(alpha, m)])
    lo, hi = chi2_interval(adev, edf)
    return AllanCurve(taus, m, adev, lo, hi, edf, alpha, float(rate_hz), n)


def allan_curves(X: np.ndarray, rate_hz: float, m: np.ndarray) -> list[AllanCurve]:
    """:func:`allan_curve` of each column of ``X`` (n samples, k channels) at cluster sizes
    ``m``: the overlapping Allan deviation as ``allantools.oadev`` defines it (from the
    phase, the cumulative sum of the mean-removed rates), each cluster size's noise type by
    :func:`identify_alpha`'s rule on the sums of m rates taken from the phase (the lag-1
    autocorrelation does not see their scale: the averages' type; for a power of two m the
    same bits), and Greenhall's edf and the chi-square interval of all channels at once.
    For many short records (a unit's static steps): no allantools call and no BLAS thread
    limit, whose fixed costs exceed the arithmetic there; one channel at a time."""
    X = np.asarray(X, float)
    n, k = X.shape
    m = np.asarray(m, int)
    m = m[m <= max(1, n // MIN_CLUSTERS)]
    if m.size == 0 or n < 2 * MIN_CLUSTERS:
        raise ValueError(f"a record of {n} samples is too short for an Allan deviation")
    rate = float(rate_hz)
    ms = m.tolist()
    adev = np.empty((k, m.size))
    alpha = np.empty((k, m.size), int)
    # the sums of m rates, D_m[i] = phase[i + m] - phase[i], give both the overlapping Allan
    # variance (their differences D_m[i + m] - D_m[i]) and the noise type (every m-th of them)
    phases = _phases(X)
    sums = np.empty(n + 1)
    v = np.empty(n + 1)
    for i in range(k):
        phase = phases[i]
        last, stepped = 0, False
        for j, mj in enumerate(ms):
            cnt = n + 1 - 2 * mj
            d_m = sums[: n + 1 - mj]
            np.subtract(phase[mj:], phase[: n + 1 - mj], out=d_m)
            d = v[:cnt]
            np.subtract(d_m[mj:], d_m[:cnt], out=d)
            adev[i, j] = np.sqrt(np.dot(d, d) / (2.0 * cnt)) / mj
            n_avg = min(n // mj, MAX_NOISE_ID_POINTS)
            if n_avg >= MIN_NOISE_ID_POINTS:
                last = _alpha_of_averages(d_m[: n_avg * mj : mj])
            elif not stepped:  # too few averages to tell: the next redder type, smaller edf
                last, stepped = max(last - 1, -2), True
            alpha[i, j] = last
    edf = np.array([[equivalent_dof(int(a), mj, n) for a, mj in zip(row, ms)] for row in alpha.tolist()])
    lo, hi = chi2_interval(adev, edf)
    tau = m.astype(float) / rate
    return [AllanCurve(tau, m, adev[i], lo[i], hi[i], edf[i], alpha[i], rate, n) for i in range(k)]


def _phases(X: np.ndarray) -> np.ndarray:
    """(k, n + 1): the phase of each column of ``X`` (n, k) times the rate, the cumulative
    sum of the mean-removed rates from 0. Two channels at a time as one complex cumulative
    sum: its real and imaginary parts add separately, so each channel gets its own sums in
    its own order, and the sequential sum (one dependent addition a sample) costs one
    channel's time for two."""
    n, k = X.shape
    out = np.empty((k, n + 1))
    out[:, 0] = 0.0
    both = np.empty(n, np.complex128)
    for j in range(0, k - 1, 2):
        x0, x1 = X[:, j], X[:, j + 1]
        np.subtract(x0, np.add.reduce(x0) / n, out=both.real)  # x0 - x0.mean()
        np.subtract(x1, np.add.reduce(x1) / n, out=both.imag)
        np.cumsum(both, out=both)
        out[j, 1:] = both.real
        out[j + 1, 1:] = both.imag
    if k % 2:
        x = X[:, -1]
        np.cumsum(x - np.add.reduce(x) / n, out=out[-1, 1:])
    return out
