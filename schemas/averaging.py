"""Step averaging: raw samples of one session -> :class:`calib_core.steps.StepMeans`.

Samples with ``step == -1`` are dropped, then the first ``settle_s`` of each step (measured
from the step's first sample time), then mean, standard deviation (ddof=1) and count per step
and channel are computed with ``numpy.bincount`` over the step index of every sample (no
Python loop over samples), two-pass so that large means (3600 deg/s, 32768 LSB) do not
cancel the variance. ``t_mid`` is the middle of the averaged window, ``temp_c`` the mean
recorded temperature (NaN when not recorded).

Steps left out, each named in a :class:`SessionWarning`:

- ``W_EMPTY_STEP``: the step has no sample at all;
- ``W_TOO_SHORT``: fewer than ``min_samples`` samples after settling;
- ``W_SATURATED``: a sample of the step (after settling) is at or beyond full scale. In
  physical units (deg/s, rad/s, g, m/s^2) the declared ``gyro_range_dps`` / ``accel_range_g``
  is the full scale. In raw units (LSB, V) the optional metadata keys
  ``gyro_full_scale_raw`` / ``accel_full_scale_raw`` give it. In every unit, clipping is also
  detected as a pile-up at the session's extreme value of a channel: for float (unquantised)
  outputs, that exact value in at least ``max(3, 1 %)`` of the step's samples (continuous
  noise never repeats a value); for quantised outputs (fewer distinct values than half the
  samples) in at least 25 % of the step's samples and in more than twice as many as the next
  lower value of the step (a noise tail thins out towards its extreme; a clip collects all
  beyond it). With a declared full scale the clip must be at least half of it (so that a
  coarse quantum on a 1 g step is not taken for clipping). Why clipping as well as the
  threshold: a sensor whose K is not exactly 1 clips a little below (or above) its declared
  range, and raw files may not declare a full scale at all.
  Limitation: a quantised channel that clips fewer than 25 % of a step's samples is not
  detected unless its full scale is declared (``gyro_full_scale_raw``) or, in physical units,
  reached; with noise below about half a quantum a noise tail can look like a clip.

Speed (docs/benchmarks.md): the steps table's columns are taken out of pandas once; the
sample -> step index comes from the reader (``SessionData.step_row``); per-step first / last
sample times come from the boundaries of runs of equal step index (``t`` is strictly
increasing, so a run's first and last samples are its extremes), not from ``ufunc.at`` over
every sample; means and standard deviations are ``bincount`` sums over the kept samples.
"""
from __future__ import annotations

from typing import Mapping

import numpy as np
import pandas as pd
import pyarrow as pa

from calib_core.steps import SessionKey, StepMeans
from schemas.contract import ACCEL_COLUMNS, F_REF_COLUMNS, GYRO_COLUMNS, SAMPLES_FILE, W_REF_COLUMNS
from schemas.dataset import SessionRef
from schemas.errors import (
    E_EMPTY_SESSION, W_EMPTY_STEP, W_SATURATED, W_TOO_SHORT, SessionError, SessionWarning,
)
from schemas.reader import SessionData, read_session, session_from_tables

SETTLE_TOLERANCE_S = 1e-6  # t - t0 of a sample exactly at settle_s may round to 0.4999999
CLIP_MIN_REPEATS = 3
CLIP_MIN_FRACTION = 0.01
CLIP_MIN_OF_FULL_SCALE = 0.5
QUANTISED_UNIQUE_FRACTION = 0.5  # fewer distinct values than this fraction: quantised channel
QUANTISED_MIN_FRACTION = 0.25


def _step_index(data: SessionData) -> np.ndarray:
    """Row of steps for every sample (-1 between steps)."""
    if data.step_row is not None:
        return data.step_row
    ids = data.steps["step"].to_numpy(np.int64)
    order = np.argsort(ids, kind="stable")
    pos = np.searchsorted(ids[order], data.step)
    pos = np.clip(pos, 0, len(ids) - 1)
    idx = order[pos]
    return np.where(data.step == -1, -1, idx)


def _describe(cols: dict[str, np.ndarray], i: int) -> str:
    return (f"step {int(cols['step'][i])} ({cols['test'][i]}, {cols['up_axis'][i]} up, "
            f"{float(cols['rate_dps'][i]):g} deg/s)")


def _step_columns(steps: pd.DataFrame) -> dict[str, np.ndarray]:
    """The steps table as numpy arrays, taken out of pandas once (each column access costs
    tens of microseconds)."""
    cols = {"step": steps["step"].to_numpy(np.int64), "test": steps["test"].to_numpy(str),
            "up_axis": steps["up_axis"].to_numpy(str)}
    for name in ("rate_dps", "angle_deg", "settle_s") + W_REF_COLUMNS + F_REF_COLUMNS:
        cols[name] = steps[name].to_numpy(float)
    return cols


def _run_extremes(idx: np.ndarray, t: np.ndarray, n_steps: int
                  ) -> tuple[np.ndarray, np.ndarray]:
    """First and last ``t`` of each step (inf / -inf when absent) for ``t`` strictly
    increasing: the extremes of a step are among the ends of its runs of equal ``idx``."""
    lo = np.full(n_steps, np.inf)
    hi = np.full(n_steps, -np.inf)
    if len(idx) == 0:
        return lo, hi
    change = np.flatnonzero(idx[1:] != idx[:-1]) + 1
    starts = np.concatenate(([0], change))
    ends = np.concatenate((change - 1, [len(idx) - 1]))
    np.minimum.at(lo, idx[starts], t[starts])  # one entry per run, not per sample
    np.maximum.at(hi, idx[ends], t[ends])
    return lo, hi


def _saturation(columns: list[np.ndarray], idx: np.ndarray, count: np.ndarray, n_steps: int,
                full_scale: np.ndarray | None, names: tuple[str, ...], unit: str
                ) -> tuple[np.ndarray, list[dict]]:
    """Per step: saturated? and, for each saturated step, the first channel and why.

    ``columns`` three (m,) arrays of kept samples, ``idx`` (m,) their step row,
    ``full_scale`` (3,) or None. Counts are bincounts of the (usually empty) subsets that hit.
    """
    saturated = np.zeros(n_steps, bool)
    why: list[dict] = [None] * n_steps  # type: ignore[list-item]
    min_repeats = np.maximum(CLIP_MIN_REPEATS, CLIP_MIN_FRACTION * count)
    if len(idx) == 0:  # no sample left after settling: nothing can be saturated
        return saturated, why
    for j, name in enumerate(names):
        x = columns[j]
        quantised = None  # decided only when a repeated extreme is found (np.unique is a sort)
        if full_scale is not None:
            hits = np.bincount(idx[np.abs(x) >= full_scale[j]], minlength=n_steps)
            for i in np.flatnonzero((hits > 0) & ~saturated):
                why[i] = dict(column=name, text=(
                    f"{name} reaches the declared full scale {full_scale[j]:g} {unit} "
                    f"({int(hits[i])} sample(s))"))
            saturated |= hits > 0
        for sign in (1.0, -1.0):
            value = x.max() if sign > 0 else x.min()  # the session's extreme, this sign
            extreme = sign * value
            if full_scale is not None and extreme < CLIP_MIN_OF_FULL_SCALE * full_scale[j]:
                continue
            if extreme <= 0:
                continue
            at = x == value
            repeats = np.bincount(idx[at], minlength=n_steps)
            candidate = (repeats >= min_repeats) & (count > 0)
            if not candidate.any():
                continue
            if quantised is None:
                # continuous (float) noise never repeats a value exactly; quantised outputs do
                quantised = len(np.unique(x)) < QUANTISED_UNIQUE_FRACTION * len(x)
            if quantised:
                # a pile-up, not a quantised noise tail: at least a quarter of the step's
                # samples on the extreme code and twice as many as on the next lower value
                # (a tail thins out towards its extreme; a clip collects all beyond it)
                sx = sign * x
                sel = candidate[idx] & ~at
                next_max = np.full(n_steps, -np.inf)
                np.maximum.at(next_max, idx[sel], sx[sel])
                at_next = sel & (sx == next_max[idx])
                n_next = np.bincount(idx[at_next], minlength=n_steps)
                candidate &= (repeats >= QUANTISED_MIN_FRACTION * count) & (repeats > 2 * n_next)
            for i in np.flatnonzero(candidate & ~saturated):
                why[i] = dict(column=name, text=(
                    f"{name} clipped at {value:g} {unit} (the session's extreme value, "
                    f"repeated in {int(repeats[i])} of {int(count[i])} samples)"))
            saturated |= candidate
    return saturated, why


def average_session(data: SessionData, min_samples: int = 10
                    ) -> tuple[StepMeans, list[SessionWarning]]:
    """Average a validated session (see module docstring). Raises E_EMPTY_SESSION when no
    step is usable."""
    cols = _step_columns(data.steps)
    n_steps = len(cols["step"])
    meta = data.meta
    idx_all = _step_index(data)
    in_step = idx_all >= 0
    idx_in = idx_all[in_step]
    t_in = data.t[in_step]
    n_any = np.bincount(idx_in, minlength=n_steps)
    # first sample time of each step (t is strictly increasing, so the first in file order)
    t0, _ = _run_extremes(idx_in, t_in, n_steps)
    settle = cols["settle_s"]
    keep = in_step.copy()
    keep[in_step] = t_in - t0[idx_in] >= settle[idx_in] - SETTLE_TOLERANCE_S
    idx = idx_all[keep]
    t = data.t[keep]
    count = np.bincount(idx, minlength=n_steps)
    safe = np.maximum(count, 1)
    ok = count > 1

    def kept_columns(values: np.ndarray) -> list[np.ndarray]:
        # one contiguous 1-D array per channel: boolean indexing of a 2-D array is slower
        return [np.ascontiguousarray(values[:, j])[keep] for j in range(3)]

    def mean_std(columns: list[np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
        mean = np.empty((n_steps, 3))
        std = np.full((n_steps, 3), np.nan)
        for j, x in enumerate(columns):
            mean[:, j] = np.bincount(idx, weights=x, minlength=n_steps) / safe
            dev = x - mean[:, j][idx]  # two-pass: no cancellation on large means
            ss = np.bincount(idx, weights=dev * dev, minlength=n_steps)
            std[ok, j] = np.sqrt(ss[ok] / (count[ok] - 1))
        return mean, std

    gyro_k, accel_k = kept_columns(data.gyro), kept_columns(data.accel)
    gyro, gyro_std = mean_std(gyro_k)
    accel, accel_std = mean_std(accel_k)
    t_lo, t_hi = _run_extremes(idx, t, n_steps)
    t_mid = np.full(n_steps, np.nan)
    t_mid[count > 0] = (t_lo[count > 0] + t_hi[count > 0]) / 2.0
    temp = np.full(n_steps, np.nan)
    if data.temp_c is not None:
        tc = data.temp_c[keep]
        finite = np.isfinite(tc)
        n_t = np.bincount(idx[finite], minlength=n_steps)
        s_t = np.bincount(idx[finite], weights=tc[finite], minlength=n_steps)
        temp = np.where(n_t > 0, s_t / np.maximum(n_t, 1), np.nan)

    g_fs = np.asarray(meta.gyro_range_dps, float) if meta.gyro_is_physical else (
        None if meta.gyro_full_scale_raw is None else np.asarray(meta.gyro_full_scale_raw, float))
    a_fs = np.asarray(meta.accel_range_g, float) if meta.accel_is_physical else (
        None if meta.accel_full_scale_raw is None else np.asarray(meta.accel_full_scale_raw, float))
    sat_g, why_g = _saturation(gyro_k, idx, count, n_steps, g_fs, GYRO_COLUMNS, meta.gyro_unit)
    sat_a, why_a = _saturation(accel_k, idx, count, n_steps, a_fs, ACCEL_COLUMNS, meta.accel_unit)

    warnings: list[SessionWarning] = []
    usable = np.ones(n_steps, bool)
    ids = cols["step"]
    short = (n_any == 0) | (count < min_samples)
    for i in np.flatnonzero(short | sat_g | sat_a):  # per left-out step, not per sample
        what = _describe(cols, i)
        if n_any[i] == 0:
            warnings.append(SessionWarning(W_EMPTY_STEP, f"{data.label}: {what} has no samples; "
                                           f"left out", step=int(ids[i])))
        elif count[i] < min_samples:
            warnings.append(SessionWarning(
                W_TOO_SHORT, f"{data.label}: {what} has {int(count[i])} sample(s) after "
                f"settling {settle[i]:g} s (of {int(n_any[i])}), fewer than {min_samples}; "
                f"left out", step=int(ids[i])))
        elif sat_g[i] or sat_a[i]:
            reasons = [w for w in (why_g[i], why_a[i]) if w]
            warnings.append(SessionWarning(
                W_SATURATED, f"{data.label}: {what}: " + "; ".join(r["text"] for r in reasons)
                + "; left out", step=int(ids[i]), column=reasons[0]["column"]))
        usable[i] = False
    if not usable.any():
        counts = {c: sum(w.code == c for w in warnings) for c in (W_EMPTY_STEP, W_TOO_SHORT, W_SATURATED)}
        raise SessionError(E_EMPTY_SESSION, data.label, SAMPLES_FILE,
                           "no usable step left (" + ", ".join(f"{v} {k}" for k, v in counts.items() if v)
                           + ")")
    sm = StepMeans(
        key=data.key if data.key is not None else SessionKey("", data.label, 0),
        step=ids, test=cols["test"], up_axis=cols["up_axis"],
        rate_dps=cols["rate_dps"], angle_deg=cols["angle_deg"],
        w_ref=np.column_stack([cols[c] for c in W_REF_COLUMNS]),
        f_ref=np.column_stack([cols[c] for c in F_REF_COLUMNS]),
        gyro=gyro, accel=accel, gyro_std=gyro_std, accel_std=accel_std, count=count,
        t_mid=t_mid, temp_c=temp, gyro_unit=meta.gyro_unit, accel_unit=meta.accel_unit,
        g_local=meta.g_local, sample_rate_hz=data.sample_rate_hz,
        gyro_range_dps=tuple(meta.gyro_range_dps), accel_range_g=tuple(meta.accel_range_g),
        metadata=dict(meta.provenance),
    )
    return sm.select(usable), warnings


def read_step_means(ref: SessionRef, min_samples: int = 10
                    ) -> tuple[StepMeans, list[SessionWarning]]:
    """Read, validate and average one session directory. Raises :class:`SessionError`."""
    return average_session(read_session(ref), min_samples)


def step_means_from_tables(key: SessionKey | str, steps_df: pd.DataFrame | pa.Table,
                           samples_table: pa.Table | pd.DataFrame,
                           metadata: Mapping | None = None, min_samples: int = 10
                           ) -> tuple[StepMeans, list[SessionWarning]]:
    """Validate and average in-memory tables (same rules as files)."""
    return average_session(session_from_tables(key, steps_df, samples_table, metadata),
                           min_samples)
