"""A unit's noise measured from its dataset: its long static recordings
(``lot=L/unit=U/noise/``, :mod:`schemas.noise_dataset`) or, without them, its sessions'
static steps, each through the unit's own calibration, analysed by :mod:`calib_core.noise`
and kept as :class:`calib_core.noise_fleet.UnitNoise` (the store's ``noise`` rows, the
calibration file's ``noise`` section). Used by the nightly (``flows.noise_units``) and the
Python API (``schemas.api.calibrate_unit``). Never raises on bad data: a recording that
cannot be used becomes a note naming it."""

from __future__ import annotations

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
    unit_dir: Path, lot: str, unit: str, applied, sessions: list[tuple], follow_symlinks: bool = False
) -> tuple[UnitNoise | None, list[str]]:
    """(UnitNoise or None, notes): the unit's noise model from its longest readable noise
    recording, else from the static steps of ``sessions`` ((SessionKey, session directory)
    of its good sessions), each through the calibration ``applied`` (its affine part: at
    rest the catalogue terms add a constant, which an Allan deviation does not see)."""
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
    segments, rate = static_segments(applied, sessions)
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
# white noise to ~1.5 % (one 100 Hz session of the default protocol holds ~9,000), and the
# cost of reading the sessions again and of the Allan deviation bounded (~0.24 s a unit of
# five 100 Hz sessions read whole, ~40 ms so)
MAX_STATIC_SAMPLES = 8192


def static_segments(
    applied, sessions: list[tuple], max_samples: int = MAX_STATIC_SAMPLES
) -> tuple[list[np.ndarray], float]:
    """The calibrated samples (affine part) of every static step after settling of the
    sessions ((SessionKey, directory)), in order, until ``max_samples`` are gathered, and
    their sample rate."""
    from schemas.dataset import SessionRef
    from schemas.reader import read_session

    segments, rates = [], []
    for key, path in sessions:
        try:
            data = read_session(SessionRef(key, Path(path)))
        except SessionError:
            continue
        steps = data.steps
        static = steps[steps["test"].isin(STATIC_TESTS) & (steps["rate_dps"].abs() == 0)]
        kept = []
        for sid, settle in zip(static["step"].to_numpy(), static["settle_s"].to_numpy(float)):
            idx = np.flatnonzero(data.step == sid)
            if len(idx):
                kept.append(idx[data.t[idx] - data.t[idx[0]] >= settle - 1e-6])
        if not kept:
            continue
        rows = np.concatenate(kept)
        w, f = applied.apply_affine(data.gyro[rows], data.accel[rows])
        both = np.hstack([w, f])
        start = 0
        for k in kept:
            segments.append(both[start : start + len(k)])
            start += len(k)
        rates.append(data.sample_rate_hz)
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
