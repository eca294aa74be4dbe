"""Noise discovery for one static recording, with the discipline of model discovery.

Per channel:

1. **Periodic lines.** Welch's spectral density against its running median: a bin is a line
   when it exceeds the chi-square quantile of the estimate at ``LINE_ALPHA`` / (number of
   bins), on the whole record AND on each half separately (a line one half does not show is
   not named). Its frequency is refined by parabolic interpolation, its amplitude taken
   from the power above the median in the line's bins (A = sqrt(2 P)).
2. **Allan deviation** of the whole record and of each half (:mod:`calib_core.noise.allan`).
3. **Processes.** The model starts as the simulator's own (white + bias instability). Each
   further process (quantization, random walk, ramp, a Gauss-Markov process with the
   correlation time that fits best) is fitted on one half: it must lower that half's chi-square
   by the ``SELECTION_ALPHA`` quantile (Bonferroni over the correlation times tried) AND,
   with the coefficients fitted there, lower the other half's chi-square by the
   ``HELDOUT_ALPHA`` quantile; both ways round. The best such process is named, and the search
   repeats until none passes.
4. **Final fit** of the named processes (lines held at their spectral amplitude) to the whole
   curve (:mod:`calib_core.noise.fit`), with the goodness of fit. A process not named gets an
   upper bound from the fit that includes it.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy import ndimage, signal, stats

from calib_core.noise import units
from calib_core.noise.allan import AllanCurve, allan_curve
from calib_core.noise.fit import AllanFit, Line, Term, fit_allan, model_avar, weighted_chi2
from calib_core.noise.model import COEFFICIENTS, ChannelNoise, NoiseModel

BASE_TERMS = (Term("white"), Term("bias_instability"))
CANDIDATES = ("quantization", "random_walk", "ramp", "gauss_markov")
SELECTION_ALPHA = 0.01
HELDOUT_ALPHA = 0.05
LINE_ALPHA = 0.01
LINE_MEDIAN_BINS = 33  # running-median window of the spectral baseline
LINE_HALF_WIDTH = 3  # bins either side of a line's peak that hold its power (Hann window)
MIN_SAMPLES = 256
# A named coefficient's interval also holds its interval in the model that adds these
# processes where discovery left them out: a random walk or quantization the record cannot
# tell apart from bias instability or white noise widens their intervals instead of
# biasing them unseen.
UNCERTAINTY_TERMS = ("random_walk",)


@dataclass(frozen=True)
class SpectralLine:
    frequency_hz: float
    amplitude: float
    ratio: float  # peak density / running median (whole record)
    ratio_halves: tuple[float, float]
    threshold: float
    resolution_hz: float  # Welch bin width: the ratio depends on it


@dataclass(frozen=True)
class DiscoveryStep:
    """One candidate process tried in one round: chi-square drops on the half that shaped
    it (``gain_fit``) and on the other half (``gain_heldout``), both ways round."""

    round: int
    process: str
    correlation_time_s: float | None
    gain_fit: tuple[float, float]
    gain_heldout: tuple[float, float]
    threshold_fit: float
    threshold_heldout: float
    named: bool

    def to_dict(self) -> dict:
        return {
            "round": self.round,
            "process": self.process,
            "correlation_time_s": self.correlation_time_s,
            "chi2_gain_fit_halves": list(self.gain_fit),
            "chi2_gain_heldout_halves": list(self.gain_heldout),
            "threshold_fit": self.threshold_fit,
            "threshold_heldout": self.threshold_heldout,
            "named": self.named,
        }


@dataclass(frozen=True)
class ChannelAnalysis:
    name: str
    unit: str
    curve: AllanCurve
    fit: AllanFit
    lines: tuple[SpectralLine, ...]
    steps: tuple[DiscoveryStep, ...]
    noise: ChannelNoise

    def to_dict(self) -> dict:
        d = self.noise.to_dict()
        d["allan"] = self.curve.to_dict()
        d["periodic"] = [
            {
                "frequency_hz": ln.frequency_hz,
                "amplitude": ln.amplitude,
                "unit": self.unit,
                "psd_ratio_to_median": ln.ratio,
                "psd_ratio_halves": list(ln.ratio_halves),
                "threshold": ln.threshold,
                "spectral_resolution_hz": ln.resolution_hz,
            }
            for ln in self.lines
        ]
        d["fit"] = {
            "processes": [
                t.name if t.correlation_time_s is None else f"gauss_markov({t.correlation_time_s:g} s)"
                for t, c in zip(self.fit.terms, self.fit.c)
            ],
            "model_adev": np.sqrt(self.fit.model_avar).tolist(),
            **self.fit.goodness(),
            "discovery": [s.to_dict() for s in self.steps],
            "method": "weighted non-negative least squares on the whole Allan variance curve",
        }
        return d


@dataclass(frozen=True)
class NoiseAnalysis:
    """Result of :func:`analyse_recording`: ``channels`` {name: ChannelAnalysis} and the
    measured :class:`NoiseModel` (``model``)."""

    rate_hz: float
    duration_s: float
    n_samples: int
    channels: dict[str, ChannelAnalysis] = field(default_factory=dict)

    @property
    def model(self) -> NoiseModel:
        return NoiseModel(self.rate_hz, self.duration_s, {k: c.noise for k, c in self.channels.items()})

    def kalibr(self) -> dict:
        """Kalibr's imu.yaml figures (continuous-time SI): per sensor the largest of its
        axes' white and random-walk densities; a random walk not named is its upper bound."""
        out: dict = {"update_rate": self.rate_hz}
        for kind, names in (("gyro", ("gx", "gy", "gz")), ("accel", ("ax", "ay", "az"))):
            chans = [self.channels[n] for n in names if n in self.channels]
            if not chans:
                continue
            for process in ("white", "random_walk"):
                key, unit = units.KALIBR_UNITS[(kind, process)]
                values, bounds = [], []
                for c in chans:
                    v = c.noise.coefficients.get(process)
                    if v is None:
                        v = c.noise.upper_bounds.get(process)
                        bounds.append(c.name)
                    if v is not None:
                        values.append(units.kalibr_density(process, v, c.unit))
                if values:
                    out[key] = max(values)
                    out[key + "_unit"] = unit
                    if bounds:
                        out[key + "_note"] = f"upper bound (not named on {', '.join(bounds)})"
        return out

    def to_dict(self) -> dict:
        d = self.model.to_dict()
        d["n_samples"] = self.n_samples
        d["channels"] = {k: c.to_dict() for k, c in self.channels.items()}
        d["kalibr"] = {**self.kalibr(), "convention": "continuous-time SI (Kalibr imu.yaml)"}
        return d


# --- periodic lines -------------------------------------------------------------------


def _segment_periodograms(x: np.ndarray, rate_hz: float, nperseg: int):
    """Hann-windowed periodograms of half-overlapping segments (each mean removed), one-sided
    density scaling as scipy.signal.welch: their average over any run of segments is Welch's
    estimate of that run."""
    step = nperseg // 2
    k = 1 + (x.size - nperseg) // step
    idx = np.arange(nperseg)[None, :] + step * np.arange(k)[:, None]
    seg = x[idx]
    seg = seg - seg.mean(axis=1, keepdims=True)
    win = signal.windows.hann(nperseg, sym=False)
    spec = np.abs(np.fft.rfft(seg * win, axis=1)) ** 2 / (rate_hz * float(win @ win))
    spec[:, 1:] *= 2.0
    if nperseg % 2 == 0:
        spec[:, -1] /= 2.0
    return np.fft.rfftfreq(nperseg, 1.0 / rate_hz), spec


def _welch(spec: np.ndarray):
    """Welch density from segment periodograms, its running-median baseline (scaled to the
    mean) and its equivalent degrees of freedom."""
    p = spec.mean(axis=0)
    nu = 2.0 * spec.shape[0] / 1.056  # Hann, 50 % overlap (Percival & Walden 7.3.3)
    base = ndimage.median_filter(p, size=LINE_MEDIAN_BINS, mode="nearest")
    base = base / (stats.chi2.median(nu) / nu)  # the median of chi2_nu/nu is below 1
    return p, base, nu


def find_lines(x: np.ndarray, rate_hz: float) -> list[SpectralLine]:
    """Periodic lines the whole record and both halves show (see the module docstring)."""
    n = x.size
    nperseg = int(2 ** np.clip(np.floor(np.log2(n / 16)), 6, 12))
    f, spec = _segment_periodograms(x, rate_hz, nperseg)
    p, base, nu = _welch(spec)
    bins = f.size
    lo_bin = LINE_MEDIAN_BINS  # the lowest bins sit on the steep red part of the spectrum
    thr = stats.chi2.ppf(1.0 - LINE_ALPHA / bins, nu) / nu
    ratio = p / base
    k_half = spec.shape[0] // 2  # segments wholly in the first / second half (one may straddle)
    halves = [_welch(spec[:k_half]), _welch(spec[-k_half:])]
    half_ratio = [hp / hb for hp, hb, _ in halves]
    half_thr = [stats.chi2.ppf(1.0 - LINE_ALPHA / bins, hnu) / hnu for *_, hnu in halves]
    lines = []
    peaks, _ = signal.find_peaks(ratio)
    for k in peaks:
        if k < lo_bin or k >= bins - 1 or ratio[k] <= thr:
            continue
        near = slice(max(k - 1, 0), k + 2)
        rh = tuple(float(r[near].max()) for r in half_ratio)
        if not all(r > t for r, t in zip(rh, half_thr)):
            continue
        a, b, c = np.log(p[k - 1 : k + 2])
        shift = 0.5 * (a - c) / (a - 2 * b + c) if (a - 2 * b + c) != 0 else 0.0
        freq = float(f[k] + np.clip(shift, -0.5, 0.5) * (f[1] - f[0]))
        span = slice(max(k - LINE_HALF_WIDTH, 1), k + LINE_HALF_WIDTH + 1)
        floor = base[span] * stats.chi2.median(nu) / nu
        power = float(np.sum(np.maximum(p[span] - floor, 0.0)) * (f[1] - f[0]))
        lines.append(
            SpectralLine(freq, float(np.sqrt(2.0 * power)), float(ratio[k]), rh, float(thr), float(f[1]))
        )
    return lines


# --- discovery ------------------------------------------------------------------------


def _correlation_times(rate_hz: float, duration_s: float) -> list[float]:
    """Gauss-Markov correlation times tried: 4 samples to 1/8 of the record, a factor 4 apart
    (the Allan variance of a Gauss-Markov process changes little for a factor 2)."""
    lo, hi = 4.0 / rate_hz, duration_s / 8.0
    if hi <= lo:
        return []
    return list(lo * 4.0 ** np.arange(int(np.floor(np.log(hi / lo) / np.log(4.0))) + 1))


def _held_chi2(fit: AllanFit, other: AllanCurve) -> float:
    return weighted_chi2(other.avar, model_avar(fit, other.tau_s, other.rate_hz), other.edf, fit.correlation)


def discover_terms(halves: tuple[AllanCurve, AllanCurve], lines: tuple[Line, ...], duration_s: float):
    """Forward selection of processes beyond white + bias instability (module docstring)."""
    terms = BASE_TERMS
    steps: list[DiscoveryStep] = []
    thr_held = float(stats.chi2.ppf(1.0 - HELDOUT_ALPHA, 1))
    pairs = (halves, halves[::-1])  # (half that shapes the fit, half that judges it)
    for rnd in range(len(CANDIDATES)):
        base = [fit_allan(shape, terms, lines) for shape, _ in pairs]
        base_held = [_held_chi2(f, other) for f, (_, other) in zip(base, pairs)]
        best = None
        named_names = {t.name for t in terms}
        round_steps = []
        for name in CANDIDATES:
            if name in named_names:
                continue
            options = (
                [Term(name, tc) for tc in _correlation_times(halves[0].rate_hz, duration_s / 2.0)]
                if name == "gauss_markov"
                else [Term(name)]
            )
            if not options:
                continue
            thr_fit = float(stats.chi2.ppf(1.0 - SELECTION_ALPHA / len(options), 1))
            scored = []
            for term in options:
                fits = [fit_allan(shape, terms + (term,), lines) for shape, _ in pairs]
                gfit = tuple(b.chi2 - f.chi2 for b, f in zip(base, fits))
                ghel = tuple(bh - _held_chi2(f, other) for bh, f, (_, other) in zip(base_held, fits, pairs))
                scored.append((min(gfit), term, gfit, ghel))
            _, term, gfit, ghelds = max(scored, key=lambda s: s[0])
            passes = min(gfit) > thr_fit and min(ghelds) > thr_held
            step = DiscoveryStep(rnd, name, term.correlation_time_s, gfit, ghelds, thr_fit, thr_held, False)
            round_steps.append(step)
            if passes and (best is None or min(ghelds) > min(best[1].gain_heldout)):
                best = (term, step)
        if best is None:
            steps.extend(round_steps)
            break
        steps.extend(
            DiscoveryStep(**{**s.__dict__, "named": True}) if s is best[1] else s for s in round_steps
        )
        terms = terms + (best[0],)
    return terms, steps


def _not_named_reason(name: str, steps) -> str:
    tried = [s for s in steps if s.process == name]
    if not tried:
        return "not tried"
    s = tried[-1]
    return (
        f"not named: adding it lowers the chi-square of the half that fits it by "
        f"{min(s.gain_fit):.1f} (needs > {s.threshold_fit:.1f}) and of the other half by "
        f"{min(s.gain_heldout):.1f} (needs > {s.threshold_heldout:.1f})"
    )


def analyse_channel(
    name: str, x: np.ndarray, rate_hz: float, unit: str, resolution: float | None = None
) -> ChannelAnalysis:
    """Discovery and final fit of one channel (rate samples ``x`` in ``unit``)."""
    units.channel_kind(unit)
    x = np.asarray(x, float)
    n = x.size
    duration = n / rate_hz
    spectral = tuple(find_lines(x, rate_hz))
    lines = tuple(Line(s.frequency_hz, s.amplitude) for s in spectral)
    curve = allan_curve(x, rate_hz)
    h = n // 2
    halves = (
        allan_curve(x[:h], rate_hz, curve.m, curve.alpha),
        allan_curve(x[h : 2 * h], rate_hz, curve.m, curve.alpha),
    )
    terms, steps = discover_terms(halves, lines, duration)
    fit = fit_allan(curve, terms, lines)
    coefficients, intervals, reasons, upper = {}, {}, {}, {}
    gm = gm_interval = None
    confounders = tuple(Term(p) for p in UNCERTAINTY_TERMS if p not in {t.name for t in terms})
    wide = fit_allan(curve, terms + confounders, lines) if confounders else fit
    for term, c in zip(fit.terms, fit.c):
        lo, hi = fit.interval(term.name)
        wlo, whi = wide.interval(term.name)
        lo, hi = min(lo, wlo), max(hi, whi)
        if term.name == "gauss_markov":
            gm, gm_interval = (float(np.sqrt(c)), float(term.correlation_time_s)), (lo, hi)
        else:
            coefficients[term.name], intervals[term.name] = float(np.sqrt(c)), (lo, hi)
    for process in COEFFICIENTS:
        if process in coefficients:
            continue
        reasons[process] = _not_named_reason(process, steps)
        with_it = fit_allan(curve, terms + (Term(process),), lines)
        upper[process] = with_it.interval(process)[1]
    noise = ChannelNoise(
        unit,
        coefficients,
        intervals,
        gm,
        gm_interval,
        tuple((ln.frequency_hz, ln.amplitude) for ln in lines),
        resolution,
        reasons,
        upper,
    )
    return ChannelAnalysis(name, unit, curve, fit, spectral, tuple(steps), noise)


def analyse_recording(
    channels: dict[str, np.ndarray],
    rate_hz: float,
    units_by_channel: dict[str, str],
    resolution: dict[str, float] | None = None,
) -> NoiseAnalysis:
    """Noise analysis of a static recording: ``channels`` {gx, gy, gz (deg/s or rad/s), ax,
    ay, az (g or m/s^2)} of equal length, sampled at ``rate_hz``; ``units_by_channel`` the unit
    of each; ``resolution`` the output step of each channel in its unit (raw counts' LSB), if
    known. ValueError (one line) on a channel that is too short, not finite or in no
    physical unit."""
    if not rate_hz or rate_hz <= 0:
        raise ValueError("the sample rate must be positive")
    sizes = {np.asarray(v).size for v in channels.values()}
    if len(sizes) != 1:
        raise ValueError("the channels differ in length")
    n = sizes.pop()
    if n < MIN_SAMPLES:
        raise ValueError(f"{n} samples: a noise analysis needs at least {MIN_SAMPLES}")
    out = {}
    for name, x in channels.items():
        x = np.asarray(x, float)
        if not np.isfinite(x).all():
            raise ValueError(f"channel {name} holds non-finite values")
        if name not in units_by_channel:
            raise ValueError(f"no unit given for channel {name}")
        res = (resolution or {}).get(name)
        out[name] = analyse_channel(name, x, rate_hz, units_by_channel[name], res)
    return NoiseAnalysis(float(rate_hz), n / float(rate_hz), n, out)
