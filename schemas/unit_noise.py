"""A unit's noise measured from its dataset: its long static recordings
(``lot=L/unit=U/noise/``, :mod:`schemas.noise_dataset`) or, without them, its sessions'
static steps, each through the unit's own calibration, analysed by :mod:`calib_core.noise`
and kept as :class:`calib_core.noise_fleet.UnitNoise` (the store's ``noise`` rows, the
calibration file's ``noise`` section). Used by the nightly (``flows.noise_units``) and the
Python API (``schemas.api.calibrate_unit``). Never raises on bad data: a recording that
cannot be used becomes a note naming it."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from calib_core.noise_fleet import CHANNELS, UnitNoise, analyse_static_steps, static_step_record, unit_noise
from schemas.errors import SessionError

GYRO_UNIT, ACCEL_UNIT = "deg/s", "g"  # what the unit's calibration outputs
CHANNEL_UNITS = tuple(GYRO_UNIT if c.startswith("g") else ACCEL_UNIT for c in CHANNELS)
STATIC_TESTS = ("multiposition", "stationary")


def analyse_channels(data: np.ndarray, rate_hz: float) -> dict:
    """The noise analysis document (``mimucal noise --json``'s shape) of a calibrated (n, 6)
    record: gx gy gz in deg/s, ax ay az in g."""
    from calib_core.noise import analyse_recording

    channels = {c: np.ascontiguousarray(data[:, i]) for i, c in enumerate(CHANNELS)}
    return analyse_recording(channels, rate_hz, dict(zip(CHANNELS, CHANNEL_UNITS))).to_dict()


def measure_unit_noise(
    unit_dir: Path,
    lot: str,
    unit: str,
    applied,
    sessions: list[tuple],
    follow_symlinks: bool = False,
    static: Mapping | None = None,
) -> tuple[UnitNoise | None, list[str]]:
    """(UnitNoise or None, notes): the unit's noise model from its longest readable noise
    recording, else from the static steps of ``sessions`` ((SessionKey, session directory)
    of its good sessions), each through the calibration ``applied`` (its affine part: at
    rest the catalogue terms add a constant, which an Allan deviation does not see).
    ``static``: {SessionKey: :class:`StaticSteps`} kept from reading the sessions
    (the sessions not in it are read again)."""
    from schemas.noise_dataset import find_noise_recordings, read_noise_recording

    notes: list[str] = []
    refs, errors = find_noise_recordings(unit_dir, lot, unit, follow_symlinks)
    notes += [str(e) for e in errors]
    recordings = []
    for ref in refs:
        try:
            recordings.append(read_noise_recording(ref))
        except SessionError as exc:
            notes.append(str(exc))
    if recordings:
        rec = max(recordings, key=lambda r: len(r.t))
        w, f = applied.apply_affine(rec.gyro, rec.accel)
        try:
            doc = analyse_channels(np.hstack([w, f]), rec.rate_hz)
        except ValueError as exc:  # the analysis' one-line refusal, naming the recording
            notes.append(f"{rec.ref.label}: no noise model ({exc})")
            return None, notes
        others = [r.ref.name for r in recordings if r is not rec]
        if others:
            notes.append(
                f"noise model from recording {rec.ref.name!r}, the longest; not used: {', '.join(others)}"
            )
        return unit_noise(doc, f"recording {rec.ref.name}", notes=notes), notes
    segments, rate = static_segments(applied, sessions, kept=static)
    if not segments:
        notes.append(f"unit {lot}/{unit}: no noise recording and no static step to measure the noise on")
        return None, notes
    try:
        record, shortest = static_step_record(segments)
        doc = analyse_static_steps(record, rate, shortest / rate, CHANNEL_UNITS)
    except ValueError as exc:
        notes.append(f"unit {lot}/{unit}: no noise model from the static steps ({exc})")
        return None, notes
    source = f"static steps ({len(segments)} steps, {shortest / rate:.3g} s at the shortest)"
    return unit_noise(doc, source, static_steps_s=shortest / rate, notes=notes), notes


# the static steps' record is cut at the session that brings it to this many samples: the
# white noise to ~1.5 % (one 100 Hz session of the default protocol holds ~9,000) and the
# Allan deviation's cost bounded
MAX_STATIC_SAMPLES = 8192


@dataclass(frozen=True)
class StaticSteps:
    """One session's static steps (``multiposition`` / ``stationary``, rate 0) after
    settling, as read (the session's units, no calibration applied): the samples the unit's
    noise is measured on when it has no long recording. The unit pipeline keeps them from
    its one read of the session (:func:`static_steps`), so that the noise model needs no
    second read."""

    gyro: np.ndarray  # (m, 3) the static steps' samples, step after step
    accel: np.ndarray  # (m, 3)
    lengths: tuple[int, ...]  # samples of each static step with samples, in steps-table order
    rate_hz: float

    @property
    def n_samples(self) -> int:
        return len(self.gyro)


def static_steps(data) -> StaticSteps:
    """The :class:`StaticSteps` of a read session (:class:`schemas.reader.SessionData`):
    every static step's samples in sample order, kept from ``settle_s`` after the step's
    first sample (``t - t0 >= settle_s - 1e-6``, as the averaging keeps them), the steps in
    the steps table's order; a step with samples but none after settling has length 0. No
    lengths at all: no static step has a sample."""
    cols = data.step_columns
    if cols is None:
        from schemas.reader import StepColumns

        cols = StepColumns.from_frame(data.steps)
    is_static = np.isin(cols.test, STATIC_TESTS) & (np.abs(cols.rate_dps) == 0)
    none = StaticSteps(np.zeros((0, 3)), np.zeros((0, 3)), (), data.sample_rate_hz)
    if not is_static.any():
        return none
    rows = data.step_row
    if rows is None:
        order = np.argsort(cols.step, kind="stable")
        pos = np.clip(np.searchsorted(cols.step[order], data.step), 0, len(cols.step) - 1)
        rows = np.where(data.step == -1, -1, order[pos])
    lut = np.zeros(len(is_static) + 1, bool)  # lut[-1]: the between-steps row -1
    lut[:-1] = is_static
    sel = np.flatnonzero(lut[rows])
    if not len(sel):
        return none
    # grouped by step row (steps-table order), each step's samples in sample order
    sel = sel[np.argsort(rows[sel], kind="stable")]
    r = rows[sel]
    first = np.flatnonzero(np.concatenate(([True], r[1:] != r[:-1])))
    size = np.diff(first, append=len(r))
    t = data.t[sel]
    t0 = np.repeat(t[first], size)
    keep = t - t0 >= cols.settle_s[r] - 1e-6
    lengths = np.add.reduceat(keep, first, dtype=np.int64)
    idx = sel[keep]
    return StaticSteps(
        _rows_at(data.gyro, idx), _rows_at(data.accel, idx), tuple(lengths.tolist()), data.sample_rate_hz
    )


def _rows_at(a: np.ndarray, idx: np.ndarray, max_runs: int = 256) -> np.ndarray:
    """``a[idx]`` (a new C-ordered array) for row indices made of a few runs of consecutive
    rows (a session's static steps): one slice per run, which copies rows of a column-major
    sample block several times faster than fancy indexing."""
    breaks = np.flatnonzero(np.diff(idx) != 1) + 1
    if not len(idx) or len(breaks) >= max_runs:
        return a[idx]
    bounds = [0, *breaks.tolist(), len(idx)]
    out = np.empty((len(idx),) + a.shape[1:], a.dtype)
    np.concatenate([a[idx[s] : idx[e - 1] + 1] for s, e in zip(bounds[:-1], bounds[1:])], axis=0, out=out)
    return out


def static_segments(
    applied,
    sessions: list[tuple],
    max_samples: int = MAX_STATIC_SAMPLES,
    kept: Mapping | None = None,
) -> tuple[list[np.ndarray], float]:
    """The calibrated samples (affine part) of every static step after settling of the
    sessions ((SessionKey, directory)), in order, until ``max_samples`` are gathered, and
    their sample rate. ``kept``: {SessionKey: StaticSteps} of sessions already read
    (the unit pipeline's); the others are read here."""
    from schemas.dataset import SessionRef
    from schemas.reader import read_session

    segments, rates = [], []
    for key, path in sessions:
        if kept is not None and key in kept:
            st = kept[key]
        else:
            try:
                st = static_steps(read_session(SessionRef(key, Path(path))))
            except SessionError:
                continue
        if not st.lengths:  # no static step with a sample
            continue
        w, f = applied.apply_affine(st.gyro, st.accel)
        both = np.hstack([w, f])
        start = 0
        for n in st.lengths:
            segments.append(both[start : start + n])
            start += n
        rates.append(st.rate_hz)
        if sum(len(x) for x in segments) >= max_samples:
            break
    return segments, float(np.median(rates)) if rates else float("nan")


def recording_noise(
    unit_dir: Path, lot: str, unit: str, applied, follow_symlinks: bool = False
) -> tuple[UnitNoise | None, list[str]]:
    """(UnitNoise or None, notes): the unit's noise model from its noise recordings alone
    (:func:`measure_unit_noise` without its static steps), None when it has no readable
    one. What model discovery takes as a noise measured independently of the repetitions:
    the static steps' model comes from the repetitions themselves."""
    from schemas.noise_dataset import find_noise_recordings

    refs, _ = find_noise_recordings(unit_dir, lot, unit, follow_symlinks)
    if not refs:
        return None, []
    noise, notes = measure_unit_noise(unit_dir, lot, unit, applied, [], follow_symlinks)
    if noise is None or not noise.source.startswith("recording "):
        return None, notes
    return noise, notes
