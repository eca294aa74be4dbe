"""The samples a session's step averages are taken over.

A *run* is a maximal run of consecutive samples of one step; a *segment* is the part of a run
that the settling rule keeps (``t - t0 >= settle_s - SETTLE_TOLERANCE_S``, ``t0`` the step's
first sample time). As ``t`` is strictly increasing, the kept samples of a run are a suffix of
it, found per run (``searchsorted`` and the exact rule at the boundary, :func:`settled_from`)
instead of per sample. Every per-step quantity is a sum over segments with
``numpy.add.reduceat``, added up per step only when a step has several segments. The
*pieces* ``[0, s0), [s0, e0), [e0, s1), [s1, e1), ...`` cover every sample (the odd ones are
the segments): the reader sums the channels over them once, which is both its finiteness
check (a NaN or infinity makes its piece's sum non-finite) and the averaging's sums
(:attr:`schemas.reader.SessionData.piece_sums`).

Apart from the reader and the averaging because both use it (the averaging imports the
reader).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

SETTLE_TOLERANCE_S = 1e-6  # t - t0 of a sample exactly at settle_s may round to 0.4999999
SETTLE_SEARCH_STEPS = 8  # moves of the settling estimate before every sample is evaluated


def runs(values: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(start, end, value) of each run of equal ``values`` (end exclusive)."""
    n = len(values)
    if n == 0:
        empty = np.zeros(0, np.intp)
        return empty, empty, values[:0]
    change = np.flatnonzero(values[1:] != values[:-1]) + 1
    starts = np.concatenate(([0], change))
    ends = np.concatenate((change, [n]))
    return starts, ends, values[starts]


def per_step(values: np.ndarray, rows: np.ndarray, n_steps: int, unique: bool) -> np.ndarray:
    """Per-segment ``values`` (..., R) added up per step row -> (..., n_steps), 0 where none."""
    out = np.zeros(values.shape[:-1] + (n_steps,), values.dtype)
    if unique:  # one segment per step (the usual file): a plain scatter
        out[..., rows] = values
    else:
        np.add.at(out, (..., rows), values)
    return out


def settled_from(
    t: np.ndarray, start: np.ndarray, end: np.ndarray, t0: np.ndarray, threshold: np.ndarray
) -> np.ndarray | None:
    """First sample of each run ``[start, end)`` that the settling rule keeps (``end`` when
    none): the first ``i`` with ``t[i] - t0 >= threshold``, evaluated exactly as per sample.

    ``t`` is strictly increasing, so ``t[i] - t0`` (rounded) never decreases along a run and
    the kept samples of a run are a suffix of it. ``searchsorted(t, t0 + threshold)`` finds
    where that suffix starts up to the rounding of ``t0 + threshold``; the exact rule then
    moves each estimate back while the sample before it is kept and on while it is not
    (usually no step at all). Returns None when that takes more than a few steps (samples
    closer than the rounding; never in recorded data): the caller evaluates every sample."""
    pos = np.searchsorted(t, t0 + threshold)
    np.clip(pos, start, end, out=pos)
    for _ in range(SETTLE_SEARCH_STEPS):
        back = pos > start
        back[back] = t[pos[back] - 1] - t0[back] >= threshold[back]
        if not back.any():
            break
        pos -= back
    else:
        return None
    for _ in range(SETTLE_SEARCH_STEPS):
        on = pos < end
        on[on] = ~(t[pos[on]] - t0[on] >= threshold[on])
        if not on.any():
            return pos
        pos += on
    return None


def settled_per_sample(
    t: np.ndarray, start: np.ndarray, end: np.ndarray, t0: np.ndarray, threshold: np.ndarray
) -> np.ndarray:
    """:func:`settled_from` by evaluating the rule on every sample of every run."""
    n_runs = len(start)
    lengths = end - start
    run_of = np.repeat(np.arange(n_runs), lengths)
    sample = np.concatenate([np.arange(a, b) for a, b in zip(start, end)]) if n_runs else start
    keep = t[sample] - t0[run_of] >= threshold[run_of]
    # the kept samples of a run are a suffix: its start is the end minus their number
    return end - np.bincount(run_of, keep, minlength=n_runs).astype(np.intp)


@dataclass(frozen=True, eq=False)
class Segments:
    """The runs and kept segments of a session's samples (arrays read-only in spirit: shared
    between the reader's result and the averaging)."""

    n: int  # samples in the session
    n_steps: int  # rows of the steps table
    n_any: np.ndarray  # (n_steps,) samples of each step, settling included
    s_start: np.ndarray  # (S,) first sample of each segment
    s_end: np.ndarray  # (S,) end (exclusive) of each segment
    s_row: np.ndarray  # (S,) steps-table row of each segment
    count: np.ndarray  # (n_steps,) int64 kept samples of each step
    unique: bool  # at most one segment per step (``per_step`` is a scatter)
    bounds: np.ndarray  # [s0, e0, s1, e1, ...] without a last index equal to n (reduceat's)
    pieces: np.ndarray  # [0, *bounds]: the piece bounds; segment i is piece 2i + 1
    piece_len: np.ndarray  # (len(pieces),) samples of each piece

    @property
    def n_seg(self) -> int:
        return len(self.s_row)


def kept_segments(
    t: np.ndarray,
    r_start: np.ndarray,
    r_end: np.ndarray,
    r_row: np.ndarray,
    settle_s: np.ndarray,
    n_steps: int,
) -> Segments:
    """The :class:`Segments` of a session: ``t`` (n,) strictly increasing sample times,
    ``r_start``/``r_end``/``r_row`` its runs of samples of one step row (row -1: between
    steps), ``settle_s`` (n_steps,) each step's settling time."""
    n = len(t)
    in_step = r_row >= 0
    r_start, r_end, r_row = r_start[in_step], r_end[in_step], r_row[in_step]
    runs_unique = len(r_row) == 0 or np.bincount(r_row).max() == 1  # one run per step
    n_any = per_step(r_end - r_start, r_row, n_steps, runs_unique)
    # each step's first sample time (t is strictly increasing: a step's first sample starts
    # one of its runs)
    t0 = np.full(n_steps, np.inf)
    if runs_unique:
        t0[r_row] = t[r_start]
    else:
        np.minimum.at(t0, r_row, t[r_start])
    r_t0 = t0[r_row]
    r_thr = (settle_s - SETTLE_TOLERANCE_S)[r_row]
    kept_from = settled_from(t, r_start, r_end, r_t0, r_thr)
    if kept_from is None:
        kept_from = settled_per_sample(t, r_start, r_end, r_t0, r_thr)
    # segments: the kept part of each run (runs are maximal: adjacent ones are other steps)
    is_seg = kept_from < r_end
    s_start, s_end, s_row = kept_from[is_seg], r_end[is_seg], r_row[is_seg]
    n_seg = len(s_row)
    count = per_step((s_end - s_start).astype(np.int64), s_row, n_steps, runs_unique)
    unique = bool(runs_unique or n_seg == np.count_nonzero(count))
    # reduceat over [s0, e0, s1, e1, ...]: an index may not be n, and the last segment runs
    # to the end anyway
    bounds = np.empty(2 * n_seg, np.intp)
    bounds[0::2] = s_start
    bounds[1::2] = s_end
    if n_seg and bounds[-1] == n:
        bounds = bounds[:-1]
    pieces = np.empty(len(bounds) + 1, np.intp)
    pieces[0] = 0
    pieces[1:] = bounds
    piece_len = np.empty(len(pieces), np.intp)
    np.subtract(pieces[1:], pieces[:-1], out=piece_len[:-1])
    piece_len[-1] = n - pieces[-1]
    return Segments(n, n_steps, n_any, s_start, s_end, s_row, count, unique, bounds, pieces, piece_len)
