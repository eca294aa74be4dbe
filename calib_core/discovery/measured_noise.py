"""A measured noise model (:class:`calib_core.noise.NoiseModel`, e.g. of a unit's long static
recording) as the step-mean noise discovery tests with (:class:`NoiseDescription`), on one
unit's grid.

What the tests need is the covariance of each repetition's step means once its turn-on
biases are fitted: the steps' noise relative to the repetition's mean. For processes with
stationary increments (all of them here, random walk and flicker included) that covariance
is exact and finite, while the absolute variance of a random walk or of a flicker noise is
not. With ``gamma(k) = E[(x_(p+k) - x_p)^2] / 2`` the sampled process' variogram and step
i the mean of the m_i samples of its window W_i,

    X_ij = sum over p in W_i, q in W_j of gamma(p - q) / (m_i m_j)
    E[(ybar_i - ybar_j)^2] = 2 X_ij - X_ii - X_jj

and the covariance of the step means with their mean over the repetition's n steps removed
(J = I - 11'/n) is  J (-X) J  (the terms X_ii, X_jj are constant along a row or a column
and J removes them). Each process' variogram at sample lags k >= 1, T = 1 / rate, in the
channel unit (IEEE 952 coefficients, :mod:`calib_core.noise.processes`):

- white N (U sqrt(s)): N^2 / T (independent samples of sd N sqrt(rate));
- output resolution r, rounding of a noisy value: r^2 / 12 per sample, white;
- quantization Q (U s): the rate of an angle quantized with error sd Q, (e_k - e_(k-1)) / T:
  3 Q^2 / T^2 at lag 1, 2 Q^2 / T^2 beyond (its step mean is (e_end - e_start) / duration);
- random walk K (U / sqrt(s)): K^2 T k / 2;
- Gauss-Markov (sigma, Tc): sigma^2 (1 - exp(-k T / Tc));
- bias instability B (U): flicker noise of one-sided PSD B^2 / (pi f), band-limited at the
  Nyquist frequency and below at 1 / (the repetition's span): its components slower than
  the repetition are absorbed by the repetition's own bias. The variogram is
  c(0) - c(k), with c the inverse Fourier transform of the PSD on the frequencies of a
  record of that span (what :mod:`calib_core.noise.synthesis` draws);
- periodic line (A, f): A^2 (1 - cos(2 pi f k T)) / 2 (aliased as sampled);
- a ramp is a deterministic drift of the bias (a term of the catalogue, not noise): left out.

Discovery's noise model (:class:`~calib_core.discovery.noise.NoiseModel` with
:class:`~calib_core.discovery.noise.SerialNoise`) describes each repetition's step means as
sigma_i^2 = w_i^2 + v on the diagonal and correlation ``lam exp(-|dt| / tau)`` between steps:
w_i^2 the white-like part (white, resolution, quantization: their exact step-mean variance,
N^2 / T_i + r^2 / (12 m_i) + 2 Q^2 / T_i^2, T_i = m_i / rate), v the wander's share. Per
channel, (v, lam, tau) are fitted so that this model's covariance with the repetition's
mean removed matches the exact one above (least squares over every pair of steps, each
scaled by the steps' exact standard deviations): the tests see the noise the repetitions
carry once their biases are fitted, by the one model discovery whitens and weights with. A
measured model is independent of the repetitions, so it costs the tests no dof
(``estimated=False``).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy import optimize

from calib_core.discovery.design import UnitGrid
from calib_core.discovery.noise import NoiseDescription, SerialNoise
from calib_core.effects import CHANNELS
from calib_core.noise.model import ChannelNoise, NoiseModel

ESTIMATED_SOURCE = "estimated from the repetitions"
# a fitted wander share below this is no serial correlation (prewhitening costs nothing then)
MIN_SERIAL_SHARE = 1e-3


@dataclass(frozen=True)
class MeasuredNoise:
    """A unit's noise measured independently of its repetitions: the model and where it was
    measured (``source``, e.g. "recording static"), what the discovery JSON names."""

    model: NoiseModel
    source: str
    # descriptions already made, per grid layout (re-linearisation builds the grid again)
    _cache: dict = field(default_factory=dict, compare=False, repr=False)

    @classmethod
    def from_document(cls, doc: dict, source: str) -> MeasuredNoise:
        """From a ``mimucal noise --json`` document (or a unit's ``UnitNoise.model``)."""
        return cls(NoiseModel.from_dict(doc), source)

    @property
    def label(self) -> str:
        return f"measured: {self.source}"

    def description(self, grid: UnitGrid, rate_hz: float) -> NoiseDescription:
        """:func:`step_noise_description` on ``grid``, made once per layout of steps."""
        key = (grid.t.tobytes(), grid.count.tobytes(), grid.gcode.tobytes(), tuple(grid.groups), rate_hz)
        out = self._cache.get(key)
        if out is None:
            out = self._cache[key] = step_noise_description(self.model, grid, rate_hz)
        return out


def white_step_variance(ch: ChannelNoise, counts: np.ndarray, rate_hz: float) -> np.ndarray:
    """Step-mean variance of the white-like processes (white, resolution, quantization) of
    steps averaging ``counts`` samples at ``rate_hz`` (channel unit squared)."""
    m = np.maximum(np.asarray(counts, float), 1.0)
    dur = m / rate_hz
    res = ch.resolution or 0.0
    return ch.value("white") ** 2 / dur + res**2 / 12.0 / m + 2.0 * ch.value("quantization") ** 2 / dur**2


def variogram(ch: ChannelNoise, n_lags: int, rate_hz: float, span: int) -> np.ndarray:
    """gamma(k), k = 0..n_lags - 1, of the channel's sampled noise (see the module
    docstring); ``span``: the record length in samples that bounds the flicker below."""
    dt = 1.0 / rate_hz
    k = np.arange(n_lags, dtype=float)
    g = np.zeros(n_lags)
    nz = k > 0
    res = ch.resolution or 0.0
    g[nz] += ch.value("white") ** 2 * rate_hz + res**2 / 12.0
    q2 = ch.value("quantization") ** 2 / dt**2
    if q2 > 0:
        g[nz] += 2.0 * q2
        if n_lags > 1:
            g[1] += q2
    g += ch.value("random_walk") ** 2 * dt * k / 2.0
    if ch.gauss_markov is not None and ch.gauss_markov[0] > 0:
        sigma, tc = ch.gauss_markov
        g += sigma**2 * -np.expm1(-k * dt / tc)
    for f, a in ch.periodic:
        g += a * a * (1.0 - np.cos(2.0 * np.pi * f * k * dt)) / 2.0
    b = ch.value("bias_instability")
    if b > 0:
        n = max(int(span), n_lags, 2)
        f = np.fft.rfftfreq(n, dt)
        psd = np.zeros_like(f)
        psd[1:] = b * b / (np.pi * f[1:])
        c = np.fft.irfft(psd * rate_hz / 2.0, n)
        g += c[0] - c[:n_lags]
    return g


def centred_step_covariance(
    ch: ChannelNoise, starts: np.ndarray, counts: np.ndarray, rate_hz: float, span: int | None = None
) -> np.ndarray:
    """Exact covariance (n, n) of the means of the sample windows [starts_i, starts_i +
    counts_i) of one record of the channel's noise, with their mean over the n windows
    removed: J (-X) J (module docstring). ``span``: the record's length in samples (default:
    from the first window's start to the last window's end)."""
    s = np.asarray(starts, np.int64)
    m = np.maximum(np.asarray(counts, np.int64), 1)
    lo, hi = int(s.min()), int((s + m).max())
    span = hi - lo if span is None else int(span)
    gam = variogram(ch, hi - lo + 1, rate_hz, span)
    n = len(s)
    X = np.empty((n, n))
    kernels: dict[tuple[int, int], tuple[np.ndarray, np.ndarray]] = {}
    for i in range(n):
        for key in {(int(m[i]), int(mj)) for mj in m}:
            if key not in kernels:
                w = np.convolve(np.ones(key[0]), np.ones(key[1])) / (key[0] * key[1])
                # offsets d = p - q of p in W_i (from s_i), q in W_j (from s_j): -(m_j - 1)..m_i - 1
                kernels[key] = (w, np.arange(-(key[1] - 1), key[0]))
        for key in {(int(m[i]), int(mj)) for mj in m}:
            w, d = kernels[key]
            js = np.flatnonzero(m == key[1])
            lag = np.abs((s[i] - s[js])[:, None] + d[None, :])
            X[i, js] = gam[lag] @ w
    return _centre(-X)


def _centre(S: np.ndarray) -> np.ndarray:
    """J S J, J = I - 11'/n: a row's and a column's mean removed."""
    return S - S.mean(axis=0, keepdims=True) - S.mean(axis=1, keepdims=True) + S.mean()


def _fit_serial(cov: np.ndarray, white: np.ndarray, t: np.ndarray) -> tuple[float, float, float]:
    """(v, lam, tau) of the model white^2 + v with correlation lam exp(-|dt| / tau) between
    steps whose covariance with the mean removed best matches ``cov`` (least squares over
    every pair of steps, each scaled by the two steps' sd in ``cov``). With the steps' mean
    white variance w^2 the model is a J + b J E J (E_ij = exp(-|dt| / tau), a = (w^2 + v)
    (1 - lam), b = (w^2 + v) lam): linear in (a, b) for a given tau, so tau is searched on a
    grid and refined, and (a, b) solved in closed form with v >= 0."""
    n = len(white)
    sd = np.sqrt(np.maximum(np.diag(cov), 1e-300))
    scale = 1.0 / np.outer(sd, sd)
    dt = np.abs(t[:, None] - t[None, :])
    w2 = float(np.mean(white**2))
    c = (cov * scale).ravel()
    Jn = (np.eye(n) - 1.0 / n) * scale
    p = Jn.ravel()
    pp, pc = float(p @ p), float(p @ c)

    def solve(log_tau: float) -> tuple[float, float, float]:
        q = (_centre(np.exp(-dt / np.exp(log_tau))) * scale).ravel()
        pq, qq, qc = float(p @ q), float(q @ q), float(q @ c)
        det = pp * qq - pq * pq
        a = (pc * qq - qc * pq) / det if det > 0 else pc / pp
        b = (qc * pp - pc * pq) / det if det > 0 else 0.0
        if b < 0.0:  # no wander: a alone
            a, b = pc / pp, 0.0
        if a < 0.0:
            a, b = 0.0, max(qc / qq, 0.0)
        if a + b < w2:  # the model's variance is at least the white part: a + b = w2
            b = float(np.clip((qc - pc - w2 * (pq - pp)) / max(pp + qq - 2.0 * pq, 1e-300), 0.0, w2))
            a = w2 - b
        r = a * p + b * q - c
        return float(r @ r), a, b

    step = float(np.median(np.diff(np.sort(t)))) if n > 1 else 1.0
    lo, hi = np.log(step / 20.0), np.log(1e3 * step * n)
    grid = np.linspace(lo, hi, 40)
    costs = [solve(x)[0] for x in grid]
    k = int(np.argmin(costs))
    best = optimize.minimize_scalar(
        lambda x: solve(x)[0],
        bounds=(grid[max(k - 1, 0)], grid[min(k + 1, len(grid) - 1)]),
        method="bounded",
        options={"xatol": 1e-3},
    )
    log_tau = float(best.x) if best.fun <= costs[k] else float(grid[k])
    _, a, b = solve(log_tau)
    total = a + b
    return max(total - w2, 0.0), (b / total if total > 0 else 0.0), float(np.exp(log_tau))


def step_noise_description(model: NoiseModel, grid: UnitGrid, rate_hz: float) -> NoiseDescription:
    """The measured ``model`` (every one of gx..az, in the calibrated units deg/s and g) as
    discovery's step-mean noise on ``grid`` (repetitions sampled at ``rate_hz``): per
    channel and test group the white-like sd and the wander's sd, and per channel the
    wander's serial correlation (module docstring). Fitted on the repetition with the most
    steps (the grid's repetitions share a protocol)."""
    missing = [c for c in CHANNELS if c not in model.channels]
    if missing:
        raise ValueError(f"measured noise model lacks channel(s) {', '.join(missing)}")
    r = int(np.argmax(grid.real.sum(axis=1)))
    rows_r = np.flatnonzero(grid.real[r])
    t = grid.t[r, rows_r]
    counts = np.rint(grid.count[r, rows_r]).astype(np.int64)
    starts = np.rint(t * rate_hz - (counts - 1) / 2.0).astype(np.int64)
    lam, tau = np.zeros(6), np.ones(6)
    white_g = np.zeros((6, len(grid.groups)))
    inst = np.zeros(6)
    for c, name in enumerate(CHANNELS):
        ch = model.channels[name]
        cov = centred_step_covariance(ch, starts, counts, rate_hz)
        if not np.all(np.diag(cov) > 0):
            raise ValueError(f"measured noise model: channel {name} has no noise on the steps")
        white = np.sqrt(white_step_variance(ch, counts, rate_hz))
        v, lam_c, tau_c = _fit_serial(cov, white, t)
        inst[c] = np.sqrt(v)
        if lam_c >= MIN_SERIAL_SHARE:
            lam[c], tau[c] = lam_c, tau_c
        all_white = white_step_variance(ch, grid.count[grid.real], rate_hz)
        gcode = grid.gcode[grid.real]
        for gi in range(len(grid.groups)):
            sel = gcode == gi
            if sel.any():
                white_g[c, gi] = np.sqrt(np.mean(all_white[sel]))
    rows = tuple(
        (
            ch,
            grp,
            0,
            float(np.hypot(white_g[c, gi], inst[c])),
            float(white_g[c, gi]),
            float(inst[c]),
        )
        for c, ch in enumerate(CHANNELS)
        for gi, grp in enumerate(grid.groups)
    )
    return NoiseDescription(rows, SerialNoise(lam, tau), estimated=False, white_from_rows=True)
