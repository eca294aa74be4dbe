"""Noise records drawn from a measured :class:`~calib_core.noise.model.NoiseModel`: every
named process, its periodic lines and its quantization, each written from its own physics
(not from the Allan formulas the fit uses), so that a record made here and analysed by
:mod:`calib_core.noise.analysis` tests the fit.

- quantization Q: the rate of an angle (velocity) quantized with uniform error of standard
  deviation Q, (e_k - e_(k-1)) / T;
- white N: independent normal samples of standard deviation N sqrt(rate);
- bias instability B: flicker noise of one-sided PSD B^2 / (pi f) (IEEE 952: sigma_min =
  0.664 B) from 1 / duration to the Nyquist frequency, shaped in the frequency domain;
- random walk K: cumulative sum of normal steps of standard deviation K sqrt(T);
- ramp R: R (t - duration / 2);
- Gauss-Markov (sigma, Tc): the exact first-order autoregression of that variance and
  correlation time;
- periodic lines: A sin(2 pi f t + phi) with a uniform random phase;
- resolution: the sum rounded to the output step, if the model carries one (as if it rode on a
  constant true value at a random place within one step).
"""

from __future__ import annotations

import numpy as np
from scipy import signal

from calib_core.noise.model import ChannelNoise, NoiseModel


def flicker(n: int, rate_hz: float, b: float, rng: np.random.Generator) -> np.ndarray:
    """Flicker noise of one-sided PSD b^2 / (pi f) for 0 < f <= rate / 2."""
    if n < 2 or b == 0:
        return np.zeros(n)
    f = np.fft.rfftfreq(n, 1.0 / rate_hz)
    psd = np.zeros_like(f)
    psd[1:] = b * b / (np.pi * f[1:])
    amp = np.sqrt(psd * rate_hz * n / 4.0)
    spec = amp * (rng.standard_normal(f.size) + 1j * rng.standard_normal(f.size))
    if n % 2 == 0:  # the Nyquist bin of a real signal is real
        spec[-1] = amp[-1] * rng.standard_normal() * np.sqrt(2.0)
    return np.fft.irfft(spec, n)


def synthesize_channel(ch: ChannelNoise, n: int, rate_hz: float, rng: np.random.Generator) -> np.ndarray:
    """One channel's noise (channel unit, zero mean apart from the processes' own wander)."""
    dt = 1.0 / rate_hz
    t = np.arange(n) * dt
    x = np.zeros(n)
    q = ch.value("quantization")
    if q > 0:
        e = rng.uniform(-np.sqrt(3.0) * q, np.sqrt(3.0) * q, n + 1)
        x += np.diff(e) / dt
    w = ch.value("white")
    if w > 0:
        x += rng.normal(0.0, w * np.sqrt(rate_hz), n)
    b = ch.value("bias_instability")
    if b > 0:
        x += flicker(n, rate_hz, b, rng)
    k = ch.value("random_walk")
    if k > 0:
        x += np.cumsum(rng.normal(0.0, k * np.sqrt(dt), n))
    r = ch.value("ramp")
    if r > 0:
        x += r * (t - t[-1] / 2.0)
    if ch.gauss_markov is not None and ch.gauss_markov[0] > 0:
        sigma, tc = ch.gauss_markov
        phi = np.exp(-dt / tc)
        drive = rng.normal(0.0, sigma * np.sqrt(1.0 - phi * phi), n)
        drive[0] = rng.normal(0.0, sigma)  # start in the stationary distribution
        x += signal.lfilter([1.0], [1.0, -phi], drive)
    for f, a in ch.periodic:
        x += a * np.sin(2.0 * np.pi * f * t + rng.uniform(0.0, 2.0 * np.pi))
    if ch.resolution:  # a fixed true value at a random place within one output step
        offset = rng.uniform(0.0, ch.resolution)
        x = np.round((x + offset) / ch.resolution) * ch.resolution - offset
    return x


def synthesize(
    model: NoiseModel, n_samples: int, rate_hz: float, rng: np.random.Generator
) -> dict[str, np.ndarray]:
    """{channel: noise record of n_samples at rate_hz} for every channel of the model, in
    the channel's unit. Lines above the new Nyquist frequency alias as a sampler would."""
    if n_samples < 1 or rate_hz <= 0:
        raise ValueError("synthesis needs n_samples >= 1 and a positive rate")
    return {
        name: synthesize_channel(ch, int(n_samples), float(rate_hz), rng)
        for name, ch in model.channels.items()
    }
