"""Noise in the fleet run: a unit's measured noise model as store rows, the record it is
measured on when the unit has no long static recording, and the lot's noise flags.

The noise analysis itself (Allan deviation, the composite fit, noise discovery) is
:mod:`calib_core.noise`; this module takes its JSON document (the stable keys of
docs/noise.md: ``rate_hz``, ``duration_s``, ``channels.<ch>.{unit, allan, coefficients,
periodic, fit}``) and never recomputes what it holds.

- :class:`UnitNoise`: one unit's model, the rows of the store's ``noise`` and
  ``noise_allan`` tables (:mod:`schemas.store_noise`) and the calibration file's ``noise``
  section.
- :func:`static_step_record`: without a long recording, the turntable protocol's static
  steps, each with its own mean removed, joined into one record. Removing a step's mean
  takes out every process slower than the step, so only what short clusters see can be
  determined: quantization and the white noise (angle / velocity random walk). Bias
  instability, random walk and ramp stay null with the reason (:data:`STATIC_ONLY`), and
  the Allan curve is cut at a quarter of the shortest step.
- :func:`judge_noise`: the noise outliers of one lot, each with its reason: robust z of
  log10 of each coefficient against the lot (the coefficients are positive and spread
  multiplicatively), each unit's own interval added to the lot's scale so that a poorly
  determined coefficient is not taken for an outlier, with the family-wise threshold of
  :class:`calib_core.outliers.ThresholdTable`; and the configured limits in engineering
  units (``gyro_white = {max = "0.3 deg/sqrt(h)"}``, :mod:`schemas.limits`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import pandas as pd

from calib_core.outliers import KIND_LIMIT, Flag, Limit, ThresholdTable, robust_scale

COEFFICIENTS = ("quantization", "white", "bias_instability", "random_walk", "ramp")
# further processes the analysis may name (a row each when it does)
OPTIONAL_COEFFICIENTS = ("gauss_markov",)
CHANNELS = ("gx", "gy", "gz", "ax", "ay", "az")
SENSOR_OF = {"gx": "gyro", "gy": "gyro", "gz": "gyro", "ax": "accel", "ay": "accel", "az": "accel"}
# the coefficients static steps of a few seconds, each with its mean removed, can determine
STATIC_ONLY = ("quantization", "white")
NOISE_MODEL = "noise"  # the model name of noise flags and limits
KIND_NOISE = "noise"  # a noise coefficient unlike the lot's
Z95 = 1.959963984540054  # the 95 % interval's half width in standard deviations


@dataclass
class UnitNoise:
    """One unit's measured noise: where it was measured, the analysis document, the rows of
    the ``noise`` and ``noise_allan`` tables, and notes (recordings refused, coefficients
    the data cannot determine)."""

    source: str  # "recording <name>" or "static steps (N steps of S s)"
    duration_s: float
    rate_hz: float
    model: dict[str, Any]
    coefficient_rows: list[dict[str, Any]] = field(default_factory=list)
    allan_rows: list[dict[str, Any]] = field(default_factory=list)
    notes: list[str] = field(default_factory=list)

    def to_dict(self) -> dict[str, Any]:
        """The calibration file's ``noise`` section: the analysis in the shape of
        ``mimucal noise --json``, with where it was measured."""
        return {
            "source": self.source,
            "duration_s": self.duration_s,
            "rate_hz": self.rate_hz,
            **{k: v for k, v in self.model.items() if k not in ("rate_hz", "duration_s")},
            "notes": list(self.notes),
        }


def _num(x: Any) -> float:
    try:
        v = float(x)
    except (TypeError, ValueError):
        return float("nan")
    return v if math.isfinite(v) else float("nan")


def _coefficient(entry: Any) -> tuple[float, float, float, str | None, str | None]:
    """(value, lo, hi, unit, reason) of one coefficient entry of the document (None, a dict
    with a null value and a reason, or a dict with value/lo/hi/unit)."""
    if not isinstance(entry, dict):
        return float("nan"), float("nan"), float("nan"), None, None
    return (
        _num(entry.get("value")),
        _num(entry.get("lo")),
        _num(entry.get("hi")),
        entry.get("unit"),
        entry.get("reason"),
    )


def _reason_of(ch_doc: dict, name: str) -> str | None:
    """Why a coefficient is null, wherever the document says it."""
    for key in ("undetermined", "reasons", "null_reasons"):
        r = ch_doc.get(key)
        if isinstance(r, dict) and r.get(name):
            return str(r[name])
    return None


def unit_noise(
    doc: dict[str, Any],
    source: str,
    static_steps_s: float | None = None,
    notes: list[str] | None = None,
) -> UnitNoise:
    """The :class:`UnitNoise` of an analysis document. ``static_steps_s``: the record is
    :func:`static_step_record`'s, of steps this long at the shortest: only
    :data:`STATIC_ONLY` coefficients are kept, the others null with the reason, and the
    Allan curve is cut at a quarter of that length."""
    rate, duration = _num(doc.get("rate_hz")), _num(doc.get("duration_s"))
    rows, allan = [], []
    channels = doc.get("channels") or {}
    base = {"source": source, "duration_s": duration, "rate_hz": rate}
    nan = float("nan")
    # what the static steps cannot determine: the same reason on every channel
    static_reasons = (
        {}
        if static_steps_s is None
        else {
            name: (
                f"no long static recording: the static steps ({static_steps_s:.3g} s at the "
                f"shortest, each step's mean removed) cannot determine {name.replace('_', ' ')}; "
                f"add lot=L/unit=U/noise/<name>.parquet"
            )
            for name in COEFFICIENTS + OPTIONAL_COEFFICIENTS
            if name not in STATIC_ONLY
        }
    )
    for ch in CHANNELS:
        ch_doc = channels.get(ch)
        if not isinstance(ch_doc, dict):
            continue
        coefs = ch_doc.get("coefficients") or {}
        names = list(COEFFICIENTS) + [c for c in OPTIONAL_COEFFICIENTS if isinstance(coefs.get(c), dict)]
        for name in names:
            reason = static_reasons.get(name)
            if reason is not None:
                value = lo = hi = nan
                unit = _coefficient(coefs.get(name))[3]
            else:
                value, lo, hi, unit, reason = _coefficient(coefs.get(name))
                reason = reason or _reason_of(ch_doc, name)
                if not np.isfinite(value) and not reason:
                    reason = "not named by the analysis (not significant on this recording)"
            rows.append(
                {
                    **base,
                    "channel": ch,
                    "coefficient": name,
                    "value": value,
                    "lo": lo,
                    "hi": hi,
                    "unit_of_measure": unit,
                    "frequency_hz": nan,
                    "reason": None if np.isfinite(value) else reason,
                }
            )
        for line in ch_doc.get("periodic") or []:
            if not isinstance(line, dict):
                continue
            rows.append(
                {
                    **base,
                    "channel": ch,
                    "coefficient": "periodic",
                    "value": _num(line.get("amplitude")),
                    "lo": _num(line.get("amplitude_lo", line.get("lo"))),
                    "hi": _num(line.get("amplitude_hi", line.get("hi"))),
                    "unit_of_measure": line.get("unit"),
                    "frequency_hz": _num(line.get("frequency_hz")),
                    "reason": None,
                }
            )
        a = ch_doc.get("allan") or {}
        tau = np.asarray(a.get("tau_s") or [], float)
        fit = ch_doc.get("fit") or {}
        fit_adev = np.asarray(fit.get("model_adev") or [np.nan] * len(tau), float)
        if len(fit_adev) != len(tau):
            fit_adev = np.full(len(tau), np.nan)
        cols = [np.asarray(a.get(k) or [np.nan] * len(tau), float) for k in ("adev", "adev_lo", "adev_hi")]
        keep = slice(None) if static_steps_s is None else tau <= static_steps_s / 4.0
        adev_unit = a.get("unit") or ch_doc.get("unit")
        for t, v, v_lo, v_hi, f in zip(*(x[keep].tolist() for x in (tau, *cols, fit_adev))):
            allan.append(
                {
                    "channel": ch,
                    "tau_s": t,
                    "adev": v,
                    "adev_lo": v_lo,
                    "adev_hi": v_hi,
                    "fit_adev": f,
                    "unit_of_measure": adev_unit,
                    "source": source,
                }
            )
    model = doc
    if static_steps_s is not None:  # the calibration file says what the record can determine
        model = {**doc, "determinable": list(STATIC_ONLY), "static_steps_s": static_steps_s}
    return UnitNoise(source, duration, rate, model, rows, allan, list(notes or []))


def static_step_record(segments: list[np.ndarray], min_samples: int = 8) -> tuple[np.ndarray, float]:
    """The static steps ``segments`` (each (n_i, 6): calibrated gx gy gz ax ay az of one step
    at rest, settling left out), each minus its own mean, joined into one (n, 6) record, and
    the shortest step's sample count used. Steps shorter than ``min_samples`` are left out."""
    kept = [s for s in segments if len(s) >= min_samples]
    if not kept:
        raise ValueError(f"no static step of at least {min_samples} samples")
    joined = np.concatenate(kept).astype(float, copy=False)
    lengths = np.array([len(s) for s in kept])
    starts = np.concatenate(([0], np.cumsum(lengths)[:-1]))
    means = np.add.reduceat(joined, starts, axis=0) / lengths[:, None]
    joined -= np.repeat(means, lengths, axis=0)
    return joined, float(lengths.min())


# --- the lot's judgement -----------------------------------------------------------------
def _fmt(v: float) -> str:
    return f"{v:.3g}"


def judge_noise(
    rows: pd.DataFrame,
    limits: tuple[Limit, ...] = (),
    thresholds: ThresholdTable | None = None,
    z_threshold: float = 3.5,
    family_alpha: float = 0.01,
    min_units: int = 5,
) -> tuple[pd.DataFrame, list[Flag], str]:
    """The noise flags of one lot's ``noise`` rows: (the rows with ``flagged``,
    ``flag_reason``, ``score`` and ``lot_median`` set, the flags, a note).

    Robust rule, per channel and coefficient (periodic lines excepted) over the lot's units
    with a value: ``z = (log10 v - median) / sqrt(s^2 + se_i^2)``, ``s`` the robust scale of
    the lot's log10 values, ``se_i`` the unit's own (its 95 % interval in log10 / 3.92);
    flagged above the family-wise threshold for that many units and coefficients (both
    directions: a sensor much quieter than its lot may be stuck). A value whose interval
    reaches zero (a process the record cannot tell from none) is not judged so. Lots with fewer than
    ``min_units`` units get limits only. Limits of model ``noise`` (``gyro_white``: every
    gyro channel's white coefficient) in the unit the rows hold."""
    out = rows.copy()
    out["flagged"] = False
    out["flag_reason"] = ""
    out["score"] = np.nan
    out["lot_median"] = np.nan
    flags: list[Flag] = []
    if not len(out):
        return out, flags, ""
    lot = str(out["lot"].iloc[0])
    thresholds = thresholds if thresholds is not None else ThresholdTable()
    value = out["value"].to_numpy(float)
    lo, hi = out["lo"].to_numpy(float), out["hi"].to_numpy(float)
    coef = out["coefficient"].astype(str).to_numpy()
    chan = out["channel"].astype(str).to_numpy()
    units = out["unit"].astype(str).to_numpy()
    uom = out["unit_of_measure"].astype(object).to_numpy()
    reasons: dict[int, list[str]] = {}
    # a coefficient whose interval reaches zero is consistent with no such process: its log
    # says nothing about the unit (limits still apply to it)
    usable = np.isfinite(value) & (value > 0) & ~(lo <= 0) & (coef != "periodic")
    judged = sorted({(c, k) for c, k, u in zip(chan, coef, usable) if u})
    groups = [(c, k) for c, k in judged if np.sum(usable & (chan == c) & (coef == k)) >= min_units]
    n_units = len(set(units))
    notes = []
    if n_units >= min_units and groups:
        # one threshold per lot (one simulated layout: the lot's units, its judged
        # coefficients), used for every group, also those a unit or two lack
        thr = thresholds.robust_z((n_units,), len(groups), z_threshold, family_alpha)
        notes.append(
            f"{len(groups)} noise coefficients judged against the lot: |robust z of log10| threshold "
            f"{thr:.2f} (family-wise alpha={family_alpha:g})"
        )
        for c, k in groups:
            idx = np.flatnonzero(usable & (chan == c) & (coef == k))
            x = np.log10(value[idx])
            med = float(np.median(x))
            s = robust_scale(x)
            with np.errstate(invalid="ignore", divide="ignore"):
                se = np.log10(hi[idx] / lo[idx]) / (2 * Z95)
            se = np.where(np.isfinite(se) & (se > 0), se, 0.0)
            denom = np.sqrt(s**2 + se**2)
            z = np.where(denom > 0, (x - med) / np.where(denom > 0, denom, 1.0), 0.0)
            out.loc[out.index[idx], "score"] = z
            out.loc[out.index[idx], "lot_median"] = 10**med
            for j, i in enumerate(idx):
                if abs(z[j]) > thr:
                    u = f" {uom[i]}" if uom[i] else ""
                    ratio = value[i] / 10**med
                    why = (
                        f"noise {c} {k} {_fmt(value[i])}{u} is {ratio:.2g}x the lot median "
                        f"{_fmt(10**med)}{u} (robust z of log10 {z[j]:+.1f}, |z| > {thr:.2f})"
                    )
                    reasons.setdefault(i, []).append(f"[{KIND_NOISE}] {why}")
                    flags.append(
                        Flag(
                            lot,
                            units[i],
                            NOISE_MODEL,
                            f"{c}.{k}",
                            KIND_NOISE,
                            value[i],
                            10**med,
                            z[j],
                            thr,
                            why,
                        )
                    )
    elif judged:
        notes.append(f"{n_units} unit(s): fewer than {min_units}, noise judged against limits only")
    for lim in limits:
        if lim.model != NOISE_MODEL:
            continue
        sensor, _, k = lim.parameter.partition("_")
        idx = np.flatnonzero(
            np.isfinite(value) & (coef == k) & np.array([SENSOR_OF.get(c) == sensor for c in chan])
        )
        wrong = sorted({str(uom[i]) for i in idx if lim.unit is not None and uom[i] != lim.unit})
        if wrong:
            notes.append(
                f"limit of noise.{lim.parameter} not applied: it is in {lim.unit!r}, "
                f"the values in {', '.join(wrong)}"
            )
            continue
        for i in idx:
            v = value[i]
            for bound, side, outside in (
                (lim.min, "below limit min", lim.min is not None and not v >= lim.min),
                (lim.max, "above limit max", lim.max is not None and not v <= lim.max),
            ):
                if outside:
                    u = f" {uom[i]}" if uom[i] else ""
                    written = f" (limit {lim.written})" if lim.written else ""
                    why = f"noise {chan[i]} {k} = {_fmt(v)}{u} {side} {_fmt(bound)}{u}{written}"
                    reasons.setdefault(i, []).append(f"[{KIND_LIMIT}] {why}")
                    flags.append(
                        Flag(
                            lot,
                            units[i],
                            NOISE_MODEL,
                            f"{chan[i]}.{k}",
                            KIND_LIMIT,
                            v,
                            np.nan,
                            v - bound,
                            bound,
                            why,
                        )
                    )
    for i, rs in reasons.items():
        out.loc[out.index[i], "flagged"] = True
        out.loc[out.index[i], "flag_reason"] = "; ".join(rs)
    return out, flags, "; ".join(notes)


def analyse_static_steps(
    record: np.ndarray, rate_hz: float, shortest_s: float, channel_units: tuple[str, ...]
) -> dict[str, Any]:
    """The noise document (``mimucal noise --json``'s shape) of a :func:`static_step_record`
    (n, 6): the Allan deviation (:func:`calib_core.noise.allan.allan_curves`, the six
    channels together) at the octave cluster sizes up to a quarter of the shortest step, and
    the composite fit (:func:`calib_core.noise.fit.fit_allan_stack`) of the processes those
    clusters see, quantization and white noise; quantization is named when its 95 % interval
    excludes zero. Bias instability, random walk and ramp are left undetermined with the
    reason, without a fit: each step's mean removes them. No noise discovery and no spectral
    lines: their evidence is in what a step's mean removes too."""
    from calib_core.noise import ChannelAnalysis, ChannelNoise
    from calib_core.noise.allan import allan_curves
    from calib_core.noise.fit import Term, coefficient_intervals, fit_allan_stack

    n = len(record)
    m_max = max(1, int(shortest_s * rate_hz / 4))
    m = 2 ** np.arange(int(np.floor(np.log2(m_max))) + 1)
    channels = {}
    why_slow = "the static steps cannot determine it (each step's mean removed)"
    curves = allan_curves(np.asarray(record, float), rate_hz, m)
    fits = fit_allan_stack(curves, (Term("quantization"), Term("white")))
    # every channel's intervals at once (AllanFit.interval's, channel by channel)
    los, his = coefficient_intervals(np.array([f.c for f in fits]), np.array([f.c_se for f in fits]))
    for ch, unit, curve, fit, ch_lo, ch_hi in zip(
        CHANNELS, channel_units, curves, fits, los.tolist(), his.tolist()
    ):
        coefficients, intervals, reasons = {}, {}, {}
        for term, c, lo, hi in zip(fit.terms, fit.c, ch_lo, ch_hi):
            if term.name == "white" or lo > 0:
                coefficients[term.name], intervals[term.name] = float(np.sqrt(c)), (lo, hi)
            else:
                reasons[term.name] = "not significant on the static steps (its 95 % interval reaches 0)"
        for name in COEFFICIENTS:
            if name not in STATIC_ONLY:
                reasons[name] = why_slow
        noise = ChannelNoise(unit, coefficients, intervals, reasons=reasons)
        channels[ch] = ChannelAnalysis(ch, unit, curve, fit, (), (), noise).to_dict()
    return {"rate_hz": float(rate_hz), "duration_s": n / float(rate_hz), "n_samples": n, "channels": channels}
