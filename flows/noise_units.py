"""A unit's noise model in the nightly: its long static recordings (``lot=L/unit=U/noise/``,
:mod:`schemas.noise_recordings`) or, without them, its sessions' static steps, through the
unit's own calibration, analysed by :mod:`calib_core.noise`, kept as
:class:`calib_core.noise_fleet.UnitNoise` on the unit's outcome (``outcome.noise``) for the
store's ``noise`` tables and the calibration file. Orchestration only; never raises: a bad
recording becomes a note naming it, and the unit keeps its calibration."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from calib_core.noise_fleet import CHANNELS, UnitNoise, analyse_static_steps, static_step_record, unit_noise
from schemas.errors import SessionError

GYRO_UNIT, ACCEL_UNIT = "deg/s", "g"  # what the unit's calibration outputs
STATIC_TESTS = ("multiposition", "stationary")


def analyse_channels(data: np.ndarray, rate_hz: float) -> dict:
    """The noise analysis document (``mimucal noise --json``'s shape) of a calibrated (n, 6)
    record: gx gy gz in deg/s, ax ay az in g."""
    from calib_core.noise import analyse_recording

    channels = {c: np.ascontiguousarray(data[:, i]) for i, c in enumerate(CHANNELS)}
    units = {c: GYRO_UNIT if c.startswith("g") else ACCEL_UNIT for c in CHANNELS}
    return analyse_recording(channels, rate_hz, units).to_dict()


def measure_unit_noise(unit_dir: Path, lot: str, unit: str, applied, sessions, follow_symlinks=False):
    """(UnitNoise or None, notes): the unit's noise model from its first readable noise
    recording (the longest when there are several), else from the static steps of its
    successful ``sessions`` (``flows.unit_pipeline.SessionOutcome``), each through the
    calibration ``applied``."""
    from schemas.noise_recordings import find_noise_recordings, read_noise_recording

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
        # the affine part only: at rest the catalogue terms add a constant, which an Allan
        # deviation does not see
        w, f = applied.apply_affine(rec.gyro, rec.accel)
        doc = analyse_channels(np.hstack([w, f]), rec.rate_hz)
        others = [r.ref.name for r in recordings if r is not rec]
        if others:
            notes.append(
                f"noise model from recording {rec.ref.name!r}, the longest; not used: {', '.join(others)}"
            )
        return unit_noise(doc, f"recording {rec.ref.name}", notes=notes), notes
    segments, rate = _static_segments(applied, sessions)
    if not segments:
        notes.append(f"unit {lot}/{unit}: no noise recording and no static step to measure the noise on")
        return None, notes
    record, shortest = static_step_record(segments)
    units = tuple(GYRO_UNIT if c.startswith("g") else ACCEL_UNIT for c in CHANNELS)
    doc = analyse_static_steps(record, rate, shortest / rate, units)
    source = f"static steps ({len(segments)} steps, {shortest / rate:.3g} s at the shortest)"
    return unit_noise(doc, source, static_steps_s=shortest / rate, notes=notes), notes


def _static_segments(applied, sessions) -> tuple[list[np.ndarray], float]:
    """The calibrated samples of every static step after settling, of every successful
    session, and their sample rate."""
    from schemas.dataset import SessionRef
    from schemas.reader import read_session

    segments, rates = [], []
    for s in sessions:
        if not s.succeeded:
            continue
        try:
            data = read_session(SessionRef(s.key, Path(s.path)))
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
        # the affine part only: at rest the catalogue terms are constant over a step, and
        # each step's mean is removed anyway (static_step_record)
        w, f = applied.apply_affine(data.gyro[np.concatenate(kept)], data.accel[np.concatenate(kept)])
        both = np.hstack([w, f])
        start = 0
        for k in kept:
            segments.append(both[start : start + len(k)])
            start += len(k)
        rates.append(data.sample_rate_hz)
    return segments, float(np.median(rates)) if rates else float("nan")


def apply_noise(unit_out, unit_dir: Path | None, follow_symlinks: bool = False) -> str | None:
    """Set ``unit_out.noise`` (a calibrated unit's measured noise); returns a note (problems,
    recordings refused) or None."""
    if unit_out.applied is None or unit_dir is None:
        return None
    noise, notes = measure_unit_noise(
        unit_dir, unit_out.lot, unit_out.unit, unit_out.applied, unit_out.sessions, follow_symlinks
    )
    unit_out.noise = noise
    return "; ".join(notes) or None


def unit_noise_of(ur) -> UnitNoise | None:
    """The measured noise of a unit's result (None: not measured)."""
    return getattr(getattr(ur, "outcome", None), "noise", None)
