"""Theoretical Allan variance of each noise process, for a rate-like channel sampled at
``rate_hz`` and averaged over clusters of ``m`` samples (tau = m / rate_hz).

Coefficients are in the channel's own unit ``U`` (deg/s for gyros, g or m/s^2 for
accelerometers) and seconds, IEEE Std 952 / 1293 definitions:

=================  ================================  =====================================
process            coefficient (unit)                Allan variance
=================  ================================  =====================================
quantization       Q  (U s: angle / velocity)        3 Q^2 / tau^2
white              N  (U / sqrt(Hz) = U sqrt(s))     N^2 / tau
bias_instability   B  (U)                            flicker, floor (2 ln 2 / pi) B^2
random_walk        K  (U / sqrt(s))                  K^2 tau / 3
ramp               R  (U / s)                        R^2 tau^2 / 2
gauss_markov       sigma (U), correlation time Tc    first-order Markov (IEEE 952 C.7)
periodic           amplitude A (U), frequency f      A^2 sin^4(pi f tau) / (m sin(pi f T))^2
=================  ================================  =====================================

Where the sampled process differs from the continuous-time formula (the sinusoid near the
Nyquist frequency, a flicker process band-limited at the Nyquist frequency and a random walk
of discrete steps at the first few cluster sizes), the discrete-time value is used, so that a record made by
:mod:`calib_core.noise.synthesis` has exactly these Allan variances. Every basis function is
the Allan variance for a coefficient of 1 (a ``periodic`` line: an amplitude of 1); the
composite model is linear in the squared coefficients.
"""

from __future__ import annotations

import math
from functools import lru_cache

import numpy as np

PROCESSES = ("quantization", "white", "bias_instability", "random_walk", "ramp", "gauss_markov")
BIAS_INSTABILITY_FLOOR = math.sqrt(2.0 * math.log(2.0) / math.pi)  # 0.664: sigma_min = 0.664 B


def quantization(tau: np.ndarray) -> np.ndarray:
    return 3.0 / np.asarray(tau, float) ** 2


def white(tau: np.ndarray) -> np.ndarray:
    return 1.0 / np.asarray(tau, float)


@lru_cache(maxsize=64)
def _flicker_factor(m: int) -> float:
    """Allan variance of sampled flicker noise (one-sided PSD B^2 / (pi f) up to the Nyquist
    frequency) at cluster size m, for B = 1: (1/pi) int_0^1/2 2 sin^4(pi u m) /
    (u m^2 sin^2(pi u)) du. It tends to 2 ln 2 / pi from below as m grows."""
    if m >= 64:
        return 2.0 * math.log(2.0) / math.pi
    u = (np.arange(40_000) + 0.5) / 80_000.0  # midpoint rule on (0, 1/2]: >= 600 points a period
    integrand = 2.0 * np.sin(np.pi * u * m) ** 4 / (u * m * m * np.sin(np.pi * u) ** 2)
    return float(integrand.sum() * (0.5 / u.size) / math.pi)


def bias_instability(tau: np.ndarray, rate_hz: float) -> np.ndarray:
    m = np.rint(np.asarray(tau, float) * rate_hz).astype(int)
    return np.array([_flicker_factor(int(k)) for k in m])


def random_walk(tau: np.ndarray, rate_hz: float) -> np.ndarray:
    """K^2 tau / 3 plus the sampled walk's own K^2 T^2 / (6 tau) (steps of variance K^2 T:
    (2 m^2 + 1) / (6 m) K^2 T; 1.5 times tau/3 at m = 1)."""
    tau = np.asarray(tau, float)
    return tau / 3.0 + 1.0 / (6.0 * rate_hz**2 * tau)


def ramp(tau: np.ndarray) -> np.ndarray:
    return np.asarray(tau, float) ** 2 / 2.0


def gauss_markov(tau: np.ndarray, correlation_time_s: float) -> np.ndarray:
    """First-order Gauss-Markov of unit variance: 2 Tc / tau [1 - Tc / (2 tau) (3 - 4 e^-x +
    e^-2x)], x = tau / Tc (random walk K^2 tau/3 with K^2 = 2/Tc below Tc, white above)."""
    tau = np.asarray(tau, float)
    tc = float(correlation_time_s)
    x = tau / tc
    small = x < 1e-3
    out = np.empty_like(tau)
    xs = x[~small]
    out[~small] = 2.0 / xs * (1.0 - (3.0 - 4.0 * np.exp(-xs) + np.exp(-2.0 * xs)) / (2.0 * xs))
    out[small] = 2.0 * x[small] / 3.0  # series: 2x/3 - x^2/... (random walk limit)
    return out


def periodic(tau: np.ndarray, frequency_hz: float, rate_hz: float) -> np.ndarray:
    """A sinusoid of amplitude 1 sampled at rate_hz, averaged over clusters of m samples."""
    tau = np.asarray(tau, float)
    m = np.rint(tau * rate_hz)
    s = np.sin(np.pi * frequency_hz / rate_hz)
    if abs(s) < 1e-12:
        return np.zeros_like(tau)
    return np.sin(np.pi * frequency_hz * tau) ** 4 / (m * s) ** 2


def basis(name: str, tau: np.ndarray, rate_hz: float, correlation_time_s: float | None = None) -> np.ndarray:
    """Allan variance of process ``name`` for a coefficient of 1 (gauss_markov: sigma = 1)."""
    if name == "quantization":
        return quantization(tau)
    if name == "white":
        return white(tau)
    if name == "bias_instability":
        return bias_instability(tau, rate_hz)
    if name == "random_walk":
        return random_walk(tau, rate_hz)
    if name == "ramp":
        return ramp(tau)
    if name == "gauss_markov":
        if not correlation_time_s or correlation_time_s <= 0:
            raise ValueError("gauss_markov needs a positive correlation time")
        return gauss_markov(tau, correlation_time_s)
    raise ValueError(f"unknown noise process {name!r}")
