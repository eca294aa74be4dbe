"""Step averaging: raw samples of one session -> :class:`calib_core.steps.StepMeans`.

Samples with ``step == -1`` are dropped, then the first ``settle_s`` of each step (measured
from the step's first sample time), then mean, standard deviation (ddof=1) and count per step
and channel are computed with ``numpy.add.reduceat`` over the runs of kept samples of each
step (no Python loop over samples), two-pass so that large means (3600 deg/s, 32768 LSB) do
not cancel the variance. ``t_mid`` is the middle of the averaged window, ``temp_c`` the mean
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

Speed (docs/benchmarks.md): the steps table's columns come from the reader
(``SessionData.step_columns``, taken out of pandas once per distinct steps file), the sample ->
step index too (``SessionData.step_row``), the six channels as one ``(6, n)`` array
(``SessionData.channels``), the kept segments (``SessionData.segments``,
:mod:`schemas.segments`: each step's runs of samples without their settling part, found per
run, not per sample) and the channels' sums over them (``SessionData.piece_sums``: the
reader's finiteness check is that sum). Every per-step quantity is computed per segment
with ``np.add.reduceat`` over the segment boundaries and added up per step only when a step
has several segments. Means and standard deviations are two-pass; the sums are ``reduceat``'s
(pairwise) instead of ``bincount``'s (sequential), which changes results by rounding only (a
few ulp). The deviations are formed one channel at a time (n floats stay in the core's cache
through subtract, square and sum). Where the reader's forms are missing or stale (a
``SessionData`` built or replaced by hand) they are derived here, with the same bits.
The saturation rules need per-sample work only when a channel's kept extreme reaches the
declared full scale, or is repeated at least ``CLIP_MIN_REPEATS`` times in the whole session,
or the session has no sample left: otherwise no step can be saturated, which a bound from the
steps' means and deviations (no sample beyond ``|mean| + sqrt(sum of squared deviations)``),
or else each channel's kept extremes (one ``reduceat`` over the kept segments a side) and
their repeats counted in the segments that hold them show (:func:`_may_saturate`). The
boolean mask of kept samples is built only when the exact rules run.
"""

from __future__ import annotations

import os
from collections import Counter
from collections.abc import Mapping

import numpy as np
import pandas as pd
import pyarrow as pa

from calib_core.guards import CONSISTENCY_Z_LIMIT, NumericEvents, inconsistent_steps
from calib_core.steps import SessionKey, StepMeans
from schemas.contract import ACCEL_COLUMNS, GYRO_COLUMNS, SAMPLES_FILE
from schemas.dataset import SessionRef
from schemas.errors import (
    E_EMPTY_SESSION,
    E_TOO_MANY_STEPS_LOST,
    W_EMPTY_STEP,
    W_INCONSISTENT_STEP,
    W_NUMERIC,
    W_SATURATED,
    W_TOO_SHORT,
    SessionError,
    SessionWarning,
)
from schemas.reader import SessionData, StepColumns, read_session, session_from_tables
from schemas.segments import Segments, kept_segments, per_step, runs

CLIP_MIN_REPEATS = 3
CLIP_MIN_FRACTION = 0.01
CLIP_MIN_OF_FULL_SCALE = 0.5
QUANTISED_UNIQUE_FRACTION = 0.5  # fewer distinct values than this fraction: quantised channel
QUANTISED_MIN_FRACTION = 0.25


def _step_index(data: SessionData) -> np.ndarray:
    """Row of steps for every sample (-1 between steps)."""
    if data.step_row is not None:
        return data.step_row
    ids = _columns(data).step
    order = np.argsort(ids, kind="stable")
    pos = np.searchsorted(ids[order], data.step)
    pos = np.clip(pos, 0, len(ids) - 1)
    idx = order[pos]
    return np.where(data.step == -1, -1, idx)


def _columns(data: SessionData) -> StepColumns:
    """The steps table as numpy arrays: the reader's, or taken out of pandas here."""
    if data.step_columns is not None:
        return data.step_columns
    return StepColumns.from_frame(data.steps)


def _same_view(a: np.ndarray, b: np.ndarray) -> bool:
    """Same memory, shape, strides and dtype: ``a`` is (still) the view ``b``."""
    return (
        a.shape == b.shape
        and a.strides == b.strides
        and a.dtype == b.dtype
        and a.__array_interface__["data"][0] == b.__array_interface__["data"][0]
    )


def _channels(data: SessionData) -> np.ndarray:
    """(6, n) float64, rows gx gy gz ax ay az: the reader's array when ``gyro`` and ``accel``
    are still views of it, else a copy."""
    x = data.channels
    if (
        x is not None
        and x.dtype == np.float64
        and x.shape == (6, len(data.t))
        and _same_view(data.gyro, x[:3].T)
        and _same_view(data.accel, x[3:].T)
    ):
        return x
    return np.concatenate((np.asarray(data.gyro, np.float64).T, np.asarray(data.accel, np.float64).T))


def _describe(cols: StepColumns, i: int) -> str:
    return (
        f"step {int(cols.step[i])} ({cols.test[i]}, {cols.up_axis[i]} up, {float(cols.rate_dps[i]):g} deg/s)"
    )


def _saturation(
    columns: list[np.ndarray],
    idx: np.ndarray,
    count: np.ndarray,
    n_steps: int,
    full_scale: np.ndarray | None,
    names: tuple[str, ...],
    unit: str,
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
                why[i] = dict(
                    column=name,
                    text=(
                        f"{name} reaches the declared full scale {full_scale[j]:g} {unit} "
                        f"({int(hits[i])} sample(s))"
                    ),
                )
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
                why[i] = dict(
                    column=name,
                    text=(
                        f"{name} clipped at {value:g} {unit} (the session's extreme value, "
                        f"repeated in {int(repeats[i])} of {int(count[i])} samples)"
                    ),
                )
            saturated |= candidate
    return saturated, why


def _kept_mask(n: int, s_start: np.ndarray, s_end: np.ndarray) -> np.ndarray:
    """(n,) bool, True on the samples of the segments ``[s_start, s_end)``."""
    edges = np.empty(2 * len(s_start) + 1, np.intp)
    edges[0] = 0
    edges[1::2] = s_start
    edges[2::2] = s_end
    on = np.zeros(len(edges), bool)
    on[1::2] = True
    return np.repeat(on, np.diff(edges, append=n))


def average_session(data: SessionData, min_samples: int = 10) -> tuple[StepMeans, list[SessionWarning]]:
    """Average a validated session (see module docstring). Raises E_EMPTY_SESSION when no
    step is usable."""
    cols = _columns(data)
    n_steps = len(cols.step)
    meta = data.meta
    t = data.t
    n = len(t)
    x = _channels(data)
    seg = _segments(data, cols)
    piece_sums = data.piece_sums if seg is data.segments and x is data.channels else None
    settle = cols.settle_s
    n_any, count, s_start, s_end, s_row = seg.n_any, seg.count, seg.s_start, seg.s_end, seg.s_row
    n_seg = seg.n_seg
    bounds = seg.bounds
    ok = count > 1

    mean = np.zeros((6, n_steps))
    std = np.full((6, n_steps), np.nan)
    t_mid = np.full(n_steps, np.nan)
    temp = np.full(n_steps, np.nan)
    reach = np.full(6, np.nan)  # no bound: every channel looked at
    if n_seg:
        mean, ss = _moments(x, seg, piece_sums)
        std[:, ok] = np.sqrt(ss[:, ok] / (count[ok] - 1))
        reach = _kept_reach(mean, ss)
        t_lo = np.full(n_steps, np.inf)
        t_hi = np.full(n_steps, -np.inf)
        if seg.unique:  # one segment per step: a plain scatter
            t_lo[s_row] = t[s_start]
            t_hi[s_row] = t[s_end - 1]
        else:
            np.minimum.at(t_lo, s_row, t[s_start])
            np.maximum.at(t_hi, s_row, t[s_end - 1])
        t_mid[count > 0] = (t_lo[count > 0] + t_hi[count > 0]) / 2.0
        if data.temp_c is not None:
            unique = seg.unique
            finite = np.isfinite(data.temp_c)
            s_t = np.add.reduceat(np.where(finite, data.temp_c, 0.0), bounds)[0::2]
            n_t = np.add.reduceat(finite, bounds, dtype=np.int64)[0::2]
            s_t = per_step(s_t, s_row, n_steps, unique)
            n_t = per_step(n_t, s_row, n_steps, unique)
            temp = np.where(n_t > 0, s_t / np.maximum(n_t, 1), np.nan)

    g_fs = (
        np.asarray(meta.gyro_range_dps, float)
        if meta.gyro_is_physical
        else (None if meta.gyro_full_scale_raw is None else np.asarray(meta.gyro_full_scale_raw, float))
    )
    a_fs = (
        np.asarray(meta.accel_range_g, float)
        if meta.accel_is_physical
        else (None if meta.accel_full_scale_raw is None else np.asarray(meta.accel_full_scale_raw, float))
    )
    sat = {}
    keep = kept_idx = None
    for rows, fs, names, unit in (
        (slice(0, 3), g_fs, GYRO_COLUMNS, meta.gyro_unit),
        (slice(3, 6), a_fs, ACCEL_COLUMNS, meta.accel_unit),
    ):
        if n_seg and _may_saturate(x[rows], bounds, fs, reach[rows]):
            # the exact rules on the kept samples (rare: clipping or full scale in sight)
            if kept_idx is None:
                keep = _kept_mask(n, s_start, s_end)
                kept_idx = _step_index(data)[keep]
            kept = [np.ascontiguousarray(x[j])[keep] for j in range(6)[rows]]
            sat[rows.start] = _saturation(kept, kept_idx, count, n_steps, fs, names, unit)
        else:
            sat[rows.start] = (np.zeros(n_steps, bool), [None] * n_steps)
    (sat_g, why_g), (sat_a, why_a) = sat[0], sat[3]

    warnings: list[SessionWarning] = []
    usable = np.ones(n_steps, bool)
    ids = cols.step
    short = (n_any == 0) | (count < min_samples)
    for i in np.flatnonzero(short | sat_g | sat_a):  # per left-out step, not per sample
        what = _describe(cols, i)
        if n_any[i] == 0:
            warnings.append(
                SessionWarning(
                    W_EMPTY_STEP, f"{data.label}: {what} has no samples; left out", step=int(ids[i])
                )
            )
        elif count[i] < min_samples:
            warnings.append(
                SessionWarning(
                    W_TOO_SHORT,
                    f"{data.label}: {what} has {int(count[i])} sample(s) after "
                    f"settling {settle[i]:g} s (of {int(n_any[i])}), fewer than {min_samples}; "
                    f"left out",
                    step=int(ids[i]),
                )
            )
        elif sat_g[i] or sat_a[i]:
            reasons = [w for w in (why_g[i], why_a[i]) if w]
            warnings.append(
                SessionWarning(
                    W_SATURATED,
                    f"{data.label}: {what}: " + "; ".join(r["text"] for r in reasons) + "; left out",
                    step=int(ids[i]),
                    column=reasons[0]["column"],
                )
            )
        usable[i] = False
    if not usable.any():
        counts = {c: sum(w.code == c for w in warnings) for c in (W_EMPTY_STEP, W_TOO_SHORT, W_SATURATED)}
        raise SessionError(
            E_EMPTY_SESSION,
            data.label,
            SAMPLES_FILE,
            "no usable step left (" + ", ".join(f"{v} {k}" for k, v in counts.items() if v) + ")",
        )
    sm = StepMeans(
        key=data.key if data.key is not None else SessionKey("", data.label, 0),
        step=ids,
        test=cols.test,
        up_axis=cols.up_axis,
        rate_dps=cols.rate_dps,
        angle_deg=cols.angle_deg,
        w_ref=cols.w_ref,
        f_ref=cols.f_ref,
        gyro=mean[:3].T,
        accel=mean[3:].T,
        gyro_std=std[:3].T,
        accel_std=std[3:].T,
        count=count,
        t_mid=t_mid,
        temp_c=temp,
        gyro_unit=meta.gyro_unit,
        accel_unit=meta.accel_unit,
        g_local=meta.g_local,
        sample_rate_hz=data.sample_rate_hz,
        gyro_range_dps=tuple(meta.gyro_range_dps),
        accel_range_g=tuple(meta.accel_range_g),
        metadata=dict(meta.provenance),
        heading_deg=cols.heading_deg,
        latitude_deg=meta.latitude_deg,
        table_heading_deg=meta.table_heading_deg,
        settle_s=np.asarray(cols.settle_s, float),
    )
    # select copies every array: the result shares nothing with the reader's cache
    return sm.select(usable), warnings


def _segments(data: SessionData, cols: StepColumns) -> Segments:
    """The reader's segments of the session when it handed them over with its sample -> step
    index, else derived here."""
    if data.segments is not None and data.step_row is not None:
        return data.segments
    r_start, r_end, r_row = runs(_step_index(data))
    return kept_segments(data.t, r_start, r_end, r_row, cols.settle_s, len(cols.step))


def _moments(x: np.ndarray, seg: Segments, piece_sums: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
    """(mean, sum of squared deviations) (6, n_steps) of the channels ``x`` (6, n) over the
    kept segments (at least one). ``piece_sums``: ``x`` summed over ``seg.pieces`` (the
    reader's, else summed here)."""
    bounds, s_row, n_steps, unique = seg.bounds, seg.s_row, seg.n_steps, seg.unique
    safe = np.maximum(seg.count, 1)
    if piece_sums is not None:  # the segments are the odd pieces
        seg_sums = piece_sums[:, 1::2]
    else:
        # reduceat over [s0, e0, s1, e1, ...]: even entries are the segments' sums (odd ones
        # the gaps between them, discarded)
        seg_sums = np.add.reduceat(x, bounds, axis=1)[:, 0::2]
    mean = per_step(seg_sums, s_row, n_steps, unique) / safe
    # two-pass: deviations from the step's mean (no cancellation on large means); the
    # mean is spread over the pieces [0, b0), [b0, b1), ... that reduceat sums
    piece_mean = np.zeros((6, len(bounds) + 1))
    piece_mean[:, 1::2] = mean[:, s_row]
    # one channel at a time: its deviations (n floats) stay in the core's cache between
    # the subtract, the square and the sums (all six, 6n floats, do not)
    seg_ss = np.empty((6, seg.n_seg))
    for j in range(6):
        dev = np.repeat(piece_mean[j], seg.piece_len)
        np.subtract(x[j], dev, out=dev)
        np.multiply(dev, dev, out=dev)
        seg_ss[j] = np.add.reduceat(dev, bounds)[0::2]
    return mean, per_step(seg_ss, s_row, n_steps, unique)


# the bound's margin for rounding: relative errors of the computed mean, deviations and sum of
# squares (at most (count + 2) ulp: 2.2e-7 for a billion samples) and of the bound itself
REACH_MARGIN = 1e-6


def _kept_reach(mean: np.ndarray, sq_dev: np.ndarray) -> np.ndarray:
    """(k,) an upper bound of ``|x|`` over every kept sample of each channel, from its steps'
    means and sums of squared deviations (k, steps; a step without kept samples has both 0):
    a sample is no farther from its step's mean than the root of the sum of squares it is
    one term of, so ``|x| <= |mean| + sqrt(sum)`` (with a margin for rounding; NaN or
    infinite when a sum is, which no comparison passes)."""
    with np.errstate(over="ignore", invalid="ignore"):
        bound = (np.abs(mean) + np.sqrt(sq_dev) * (1.0 + REACH_MARGIN)) * (1.0 + REACH_MARGIN)
        return bound.max(axis=1)


def _may_saturate(
    x: np.ndarray, bounds: np.ndarray, full_scale: np.ndarray | None, reach: np.ndarray | None = None
) -> bool:
    """False when :func:`_saturation`'s rules cannot find a saturated step in these channels
    (``x`` (k, n) all samples, ``bounds`` the kept segments as given to reduceat:
    ``[s0, e0, s1, e1, ...]``): no kept sample reaches the full scale, and every kept extreme
    that the clip rule looks at occurs fewer than ``CLIP_MIN_REPEATS`` times among the kept
    samples (an upper bound of its repeats in any one step, which must reach
    ``max(CLIP_MIN_REPEATS, ...)``).

    A channel's kept extremes are reduced over the kept segments (one ``reduceat`` a side);
    its kept samples equal to an extreme lie in the segments whose extreme it is, counted
    there. ``reach`` (k,): an upper bound of every kept sample's ``|x|`` per channel
    (:func:`_kept_reach`): a channel whose bound is below both the full scale and the clip
    rule's least value is not looked at further."""
    starts = bounds[0::2]
    ends = np.append(bounds[1::2], x.shape[1]) if len(bounds) % 2 else bounds[1::2]
    for j in range(len(x)):
        fs = np.inf if full_scale is None else float(full_scale[j])
        min_look = 0.0 if full_scale is None else CLIP_MIN_OF_FULL_SCALE * fs
        if reach is not None and full_scale is not None and reach[j] < min(min_look, fs):
            continue  # no kept sample comes near full scale, nor near half of it
        for sign, red in ((1.0, np.maximum), (-1.0, np.minimum)):
            seg_extreme = red.reduceat(x[j], bounds)[0::2]  # each kept segment's
            value = seg_extreme.max() if sign > 0 else seg_extreme.min()
            extreme = sign * value
            if extreme >= fs:
                return True
            if extreme < min_look or extreme <= 0:
                continue  # the clip rule does not look at this side
            repeats = 0
            for k in np.flatnonzero(seg_extreme == value):
                repeats += np.count_nonzero(x[j, starts[k] : ends[k]] == value)
                if repeats >= CLIP_MIN_REPEATS:
                    return True
    return False


# A session that loses more than this share of its steps (left out with a warning) is
# rejected (E_TOO_MANY_STEPS_LOST) rather than calibrated from the rest: so many bad steps
# say the file, not a step, is wrong (damaged bytes that still decode turned 16 of 118 step
# ids into ids of no step). $MIMUCAL_MAX_LOST_STEP_SHARE overrides it (0..1).
MAX_LOST_STEP_SHARE = 0.05
LOST_SHARE_ENV = "MIMUCAL_MAX_LOST_STEP_SHARE"


def max_lost_step_share() -> float:
    """The share in force: $MIMUCAL_MAX_LOST_STEP_SHARE when set (a number in [0, 1]), else
    :data:`MAX_LOST_STEP_SHARE`."""
    text = os.environ.get(LOST_SHARE_ENV)
    if not text:
        return MAX_LOST_STEP_SHARE
    try:
        share = float(text)
    except ValueError:
        raise ValueError(f"${LOST_SHARE_ENV}={text!r} is not a number") from None
    if not 0.0 <= share <= 1.0:
        raise ValueError(f"${LOST_SHARE_ENV}={text!r} must be between 0 and 1")
    return share


def check_lost_steps(
    label: str, n_steps: int, warnings: list[SessionWarning], max_share: float | None = None
) -> None:
    """E_TOO_MANY_STEPS_LOST when the steps left out (one warning each) exceed the share."""
    share = max_lost_step_share() if max_share is None else max_share
    lost = [w for w in warnings if w.step is not None]
    if n_steps and len(lost) > share * n_steps:
        counts = Counter(w.code for w in lost)
        raise SessionError(
            E_TOO_MANY_STEPS_LOST,
            label,
            SAMPLES_FILE,
            f"{len(lost)} of {n_steps} steps left out ("
            + ", ".join(f"{v} {k}" for k, v in sorted(counts.items()))
            + f"), more than the {share:.0%} allowed; the session is not "
            f"calibrated from the rest",
        )


def read_step_means(
    ref: SessionRef, min_samples: int = 10, max_lost_share: float | None = None
) -> tuple[StepMeans, list[SessionWarning]]:
    """Read, validate and average one session directory. Raises :class:`SessionError`,
    also when more than ``max_lost_share`` (default :func:`max_lost_step_share`) of its
    steps are left out."""
    return session_step_means(read_session(ref), min_samples, max_lost_share)


def session_step_means(
    data: SessionData, min_samples: int = 10, max_lost_share: float | None = None
) -> tuple[StepMeans, list[SessionWarning]]:
    """:func:`read_step_means` of a session already read."""
    with NumericEvents() as numeric:
        sm, warns = average_session(data, min_samples)
    check_lost_steps(data.label, len(data.steps), warns, max_lost_share)
    if numeric:
        warns.append(numeric_warning(data.label, "averaging its steps", numeric))
    return sm, warns


def numeric_warning(label: str, stage: str, events: NumericEvents) -> SessionWarning:
    """``W_NUMERIC``: the floating-point errors NumPy met on this session (they are not
    printed: the terminal shows no RuntimeWarning), named with the session and the stage."""
    return SessionWarning(
        W_NUMERIC,
        f"{label}: floating-point {events} while {stage} (a value too large or undefined for "
        f"the arithmetic: damaged data?); the results kept are finite and passed the "
        f"plausibility checks",
    )


def step_means_from_tables(
    key: SessionKey | str,
    steps_df: pd.DataFrame | pa.Table,
    samples_table: pa.Table | pd.DataFrame,
    metadata: Mapping | None = None,
    min_samples: int = 10,
) -> tuple[StepMeans, list[SessionWarning]]:
    """Validate and average in-memory tables (same rules as files)."""
    return average_session(session_from_tables(key, steps_df, samples_table, metadata), min_samples)


def leave_out_inconsistent_steps(
    sessions: list[tuple[StepMeans, list[SessionWarning]]],
    z_limit: float = CONSISTENCY_Z_LIMIT,
    max_lost_share: float | None = None,
) -> list[tuple[StepMeans, list[SessionWarning]] | SessionError]:
    """The averaged repetitions of one unit (each with its warnings so far), each step that
    contradicts the same step in the other repetitions (:func:`calib_core.guards.
    inconsistent_steps`) left out with a ``W_INCONSISTENT_STEP`` warning; item i is session
    i's step means and warnings, or the :class:`SessionError` ``E_TOO_MANY_STEPS_LOST`` when
    the steps it has lost in all now exceed the allowed share.

    Why against the other repetitions and not the session's own fit: a damaged value inside
    the sensor's range (bytes that decode, no page checksum) is an outlier of one repetition,
    while the structured error the fit leaves out (lever arm, nonlinearity) is the same in
    every repetition and cancels in the comparison. A unit with a single repetition has
    nothing to compare with: its steps are kept (docs/hardening.md, limitations)."""
    sms = [sm for sm, _ in sessions]
    found = inconsistent_steps(sms, z_limit)
    out: list[tuple[StepMeans, list[SessionWarning]] | SessionError] = []
    for r, (sm, warns) in enumerate(sessions):
        mine = [d for d in found if d.index == r]
        if not mine:
            out.append((sm, warns))
            continue
        warns = list(warns)
        drop = np.zeros(len(sm), bool)
        for d in mine:
            i = int(np.flatnonzero(sm.step == d.step)[0])
            drop[i] = True
            unit = sm.gyro_unit if d.channel.startswith("g") else sm.accel_unit
            what = f"step {d.step} ({sm.test[i]}, {sm.up_axis[i]} up, {float(sm.rate_dps[i]):g} deg/s)"
            if d.ambiguous:
                other = sms[1 - r].key.rep
                whom = (
                    f"the same step in rep {other} by {2 * abs(d.deviation):.4g} {unit} "
                    f"(robust z {abs(d.z):.0f}, limit {z_limit:g}); two repetitions cannot tell "
                    f"which is wrong, so it is left out of both"
                )
            else:
                whom = (
                    f"the same step in the unit's other repetitions by {d.deviation:+.4g} {unit} "
                    f"(robust z {abs(d.z):.0f}, limit {z_limit:g}); left out"
                )
            warns.append(
                SessionWarning(
                    W_INCONSISTENT_STEP,
                    f"{sm.key}: {what}: {d.channel} differs from {whom}",
                    d.step,
                    d.channel,
                )
            )
        n_lost_before = sum(w.step is not None for w in sessions[r][1])
        try:
            check_lost_steps(str(sm.key), len(sm) + n_lost_before, warns, max_lost_share)
        except SessionError as exc:
            out.append(exc)
            continue
        out.append((sm.select(~drop), warns))
    return out
