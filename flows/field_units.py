"""Units calibrated from field recordings (``lot=L/unit=U/field/``, see
:mod:`schemas.field_dataset`) as the nightly runs them: every recording of the unit goes
through ``mimucal field``'s hand-held calibration (pose detection, joint accel and gyro fit;
no held-out refits), its calibration becomes one repetition (models ``gyro``/``accel`` in the
affine form with standard errors, ``field_fit`` its figures of merit), the repetitions are
averaged into the unit's calibration (kind ``field``) and model discovery runs on the static
poses of the unit's recording with the most poses
(:func:`calib_core.discovery.static.diagnose_static`).

The result is the :class:`flows.unit_pipeline.UnitResult` a turntable unit gives, so that the
nightly stores, flags and reports both alike. Never raises on bad data: a recording that
cannot be read or fitted is a failed session naming the recording, file and reason."""

from __future__ import annotations

import math
import time
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from calib_core.models.field.results import field_unit_calibration
from flows.unit_pipeline import (
    STATUS_FAILED,
    STATUS_OK,
    STATUS_WARNED,
    SessionOutcome,
    UnitJob,
    UnitOutcome,
    UnitResult,
)
from schemas.errors import E_IMPLAUSIBLE, E_MIXED_UNITS
from schemas.field_dataset import FieldRecordingRef, field_fingerprint, find_field_recordings

INIT_PREAMBLE_KEYS = ("initialization time", "init time", "initial rest", "tinit")
INT16_LIMIT = 32767.0  # an int16 output clips here
MIN_DISCOVERY_POSES = 12  # 9 accel + 3 gyro base parameters and some degrees of freedom


# --- the options of one recording (shared with ``mimucal field``) ------------------------------
def init_static_s(opts: Mapping[str, Any], preamble: Mapping[str, str]) -> float | None:
    """Seconds at rest at the start: the ``init_static`` option (0: none), else the log's
    preamble ``Initialization time`` line, else None (the detector uses the quietest
    windows)."""
    v = opts.get("init_static")
    if v is not None:
        return float(v) if v > 0 else None
    for key, value in preamble.items():
        if key.strip().lower() in INIT_PREAMBLE_KEYS:
            try:
                return float(value)
            except ValueError:
                return None
    return None


def starting_scales(
    opts: Mapping[str, Any], gyro_unit: str, accel_unit: str
) -> tuple[float | None, float | None]:
    """Starting accel scale (m/s^2 per raw unit) and gyro scale (rad/s per raw unit): the
    ``acc_scale``/``gyro_scale`` options, else the int16 full-scale ranges, else identity
    for data already in g / deg/s. ValueError when a range is given for physical units or
    does not parse."""
    from schemas.importers import FULL_SCALE_COUNTS, parse_range

    acc, gyr = opts.get("acc_scale"), opts.get("gyro_scale")
    g_local = float(opts.get("g_local") or 9.80665)
    if acc is None and opts.get("accel_range"):
        if accel_unit != "LSB":
            raise ValueError("--accel-range applies to raw counts (--accel-unit LSB)")
        acc = parse_range(opts["accel_range"], "accel") * g_local / FULL_SCALE_COUNTS
    if gyr is None and opts.get("gyro_range"):
        if gyro_unit != "LSB":
            raise ValueError("--gyro-range applies to raw counts (--gyro-unit LSB)")
        gyr = math.radians(parse_range(opts["gyro_range"], "gyro") / FULL_SCALE_COUNTS)
    if acc is None and accel_unit == "g":  # already physical: identity is the start
        acc = g_local
    if gyr is None and gyro_unit == "deg/s":
        gyr = math.radians(1.0)
    return acc, gyr


def field_fit_problems(gyro, accel, figures, move_ok) -> list:
    """:func:`calib_core.guards.check_field_fit` on a fitted recording (its affine gyro and
    accel fits and its figures after the fit): what makes it no working sensor's."""
    from calib_core.guards import check_field_fit

    s = figures.summary("", move_ok)
    return check_field_fit(s["norm_rms_mg"], s["angle_rms_deg"], gyro.K, gyro.w0, accel.K, accel.f0)


# --- planning -----------------------------------------------------------------------------------
@dataclass
class FieldUnitJob(UnitJob):
    """A unit calibrated from its field recordings (``refs``: FieldRecordingRef)."""


def plan_field_units(
    dataset: str | Path,
    previous: dict[tuple[str, str, int], str],
    force: bool = False,
    turntable_units: set[str] | frozenset[str] = frozenset(),
    unit: str | None = None,
    follow_symlinks: bool = False,
) -> tuple[list[FieldUnitJob], list[tuple[str, str]], list]:
    """Field units to calibrate (new, changed, or all with ``force``), units skipped because
    every recording's fingerprint is unchanged, and path errors (a unit that also has
    turntable sessions: a unit is calibrated one way, its field recordings are left out)."""
    from schemas.errors import E_BAD_PATH, SessionError

    refs, errors = find_field_recordings(dataset, unit=unit, follow_symlinks=follow_symlinks)
    by_unit: dict[tuple[str, str], list[FieldRecordingRef]] = {}
    for r in refs:
        if r.key.unit in turntable_units:
            errors.append(
                SessionError(
                    E_BAD_PATH,
                    str(r.key),
                    r.name,
                    f"unit {r.key.unit!r} has turntable sessions (rep=N) and field recordings; "
                    "a unit is calibrated one way: the field recordings are not used",
                )
            )
            continue
        by_unit.setdefault((r.key.lot, r.key.unit), []).append(r)
    lots_of: dict[str, set[str]] = {}
    for lot, u in by_unit:
        lots_of.setdefault(u, set()).add(lot)
    jobs, skipped = [], []
    for (lot, u), rs in sorted(by_unit.items()):
        if len(lots_of[u]) > 1:
            errors.append(
                SessionError(
                    E_BAD_PATH,
                    f"{lot}/{u}",
                    "field",
                    f"unit {u!r} appears in lots {', '.join(sorted(lots_of[u]))}; a unit belongs to one lot",
                )
            )
            continue
        before = {rep: fp for (pl, pu, rep), fp in previous.items() if (pl, pu) == (lot, u)}
        if force:
            jobs.append(FieldUnitJob(lot, u, rs, "forced"))
        elif not before:
            jobs.append(FieldUnitJob(lot, u, rs, "new"))
        elif {r.key.rep: field_fingerprint(r) for r in rs} != before:
            jobs.append(FieldUnitJob(lot, u, rs, "changed field recordings"))
        else:
            skipped.append((lot, u))
    return jobs, skipped, errors


# --- one recording, one unit --------------------------------------------------------------------
@dataclass
class _Recording:
    """What the unit keeps of one fitted recording for discovery."""

    calibration: Any  # calib_core.calibration.Calibration
    pose_means: Any  # pandas DataFrame (static_pose_means)


def calibrate_recording(ref: FieldRecordingRef) -> tuple[SessionOutcome, _Recording | None]:
    """Read and fit one recording; a failure is the session's, never raised."""
    from calib_core.errors import DesignError
    from calib_core.models.field.joint import Priors, field_figures, fit_field, usable_moves
    from calib_core.models.field.results import affine_fits, figure_fit
    from calib_core.models.field.static_detection import clipped_samples, detect_poses, static_pose_means
    from calib_core.results import RepetitionCalibration
    from schemas.errors import SessionError
    from schemas.field_dataset import read_field_recording

    try:
        fp = field_fingerprint(ref)
    except OSError:
        fp = ""
    o = ref.options
    try:
        if ref.error is not None:  # refused before any file is opened (schemas.field_dataset)
            raise ref.error
        rec = read_field_recording(ref)
        acc_scale, gyro_scale = starting_scales(o, rec.gyro_unit, rec.accel_unit)
        det = detect_poses(
            rec.t,
            rec.gyro,
            rec.accel,
            init_s=init_static_s(o, rec.metadata.get("preamble", {})),
            window_s=o["window"],
            min_pose_s=o["min_pose"],
            multiplier=o["multiplier"],
        )
        move_ok = usable_moves(
            rec.gyro, det.poses, clipped_samples(rec.gyro, INT16_LIMIT if o["gyro_range"] else None)
        )
        on_off = {"auto": "auto", "on": True, "off": False}
        fit = fit_field(
            rec.t,
            rec.gyro,
            rec.accel,
            det.poses,
            rec.g_local,
            accel_scale=acc_scale,
            gyro_scale=gyro_scale,
            accel_bias=o["acc_bias"],
            drift=on_off[o["drift"]],
            g_sensitivity=on_off[o["gyro_g_sensitivity"]],
            priors=Priors(o["misalignment_prior"] or None),
            move_use=move_ok,
            gyro_unit=rec.gyro_unit,
            accel_unit=rec.accel_unit,
            metadata={"source": rec.source},
        )
        gyro, accel = affine_fits(fit)
        figures = field_figures(fit.calibration, rec.t, rec.gyro, rec.accel, det.poses)
        implausible = field_fit_problems(gyro, accel, figures, move_ok)
        if implausible:
            raise SessionError(
                E_IMPLAUSIBLE,
                str(ref.key),
                ref.name,
                "estimates are not those of a working sensor: " + "; ".join(map(str, implausible)),
            )
    except SessionError as exc:
        return SessionOutcome(ref.key, ref.path, STATUS_FAILED, exc.code, str(exc), [], fp), None
    except (DesignError, ValueError, KeyError, ArithmeticError, np.linalg.LinAlgError) as exc:
        code = getattr(exc, "code", "E_FIELD_FIT")
        reason = (getattr(exc, "reason", None) or str(exc))[:300]
        msg = f"[{code}] session {ref.key}, file {ref.name}: {reason}"
        return SessionOutcome(ref.key, ref.path, STATUS_FAILED, code, msg, [], fp), None
    warnings = []
    if (~move_ok).any():
        warnings.append(
            f"{int((~move_ok).sum())} of {len(move_ok)} moves have a clipped gyro sample: left out of the fit"
        )
    rc = RepetitionCalibration(
        ref.key.lot,
        ref.key.unit,
        ref.key.rep,
        fits={"gyro": gyro, "accel": accel, "field_fit": figure_fit(figures, move_ok)},
        warnings=warnings,
        provenance={
            "kind": "field",
            "recording": ref.name,
            "path": str(ref.path),
            "fingerprint": fp,
            "g_local": rec.g_local,
            "session_start": o.get("session_start"),
            "n_poses": len(det.poses),
            "n_poses_rejected": len(det.rejected),
            "n_quiet_poses": int(sum(p.gyro_quiet for p in det.poses)),
            "moves_used": int(move_ok.sum()),
            "terms": [tv.name for tv in fit.calibration.terms],
        },
    )
    status = STATUS_WARNED if warnings else STATUS_OK
    out = SessionOutcome(ref.key, ref.path, status, None, None, warnings, fp, rc)
    pm = static_pose_means(rec.t, rec.gyro, rec.accel, det.intervals())
    return out, _Recording(fit.calibration, pm)


def drop_mixed_units(outcomes: list[SessionOutcome], fitted: list) -> tuple[list[SessionOutcome], list]:
    """A unit's recordings are averaged, so they must share raw units: the first fitted
    recording's units decide, a recording in other units fails (``E_MIXED_UNITS``, naming
    both). ``fitted`` runs parallel to the successful outcomes."""
    units_of = lambda o: (o.calibration.fits["gyro"].raw_unit, o.calibration.fits["accel"].raw_unit)  # noqa: E731
    good = [i for i, o in enumerate(outcomes) if o.calibration is not None]
    if not good:
        return outcomes, fitted
    first = outcomes[good[0]]
    ref = units_of(first)
    out, kept = list(outcomes), []
    for k, i in enumerate(good):
        o = outcomes[i]
        if units_of(o) == ref:
            kept.append(fitted[k])
            continue
        msg = (
            f"[{E_MIXED_UNITS}] session {o.key}, file {o.path.name}: raw units gyro {units_of(o)[0]}, "
            f"accel {units_of(o)[1]} differ from {first.path.name}'s ({ref[0]}, {ref[1]}); a unit's "
            "recordings are averaged, so they must share their raw units"
        )
        out[i] = SessionOutcome(o.key, o.path, STATUS_FAILED, E_MIXED_UNITS, msg, [], o.fingerprint)
    return out, kept


def calibrate_field_unit_job(job: UnitJob, run_discovery: bool = True) -> UnitResult:
    """Every recording of one field unit, their average, and model discovery on the static
    poses of the recording with the most poses. Never raises on bad data."""
    t0 = time.perf_counter()
    outcomes, fitted = [], []
    for ref in sorted(job.refs, key=lambda r: r.key.rep):
        try:
            o, r = calibrate_recording(ref)
        except Exception as exc:  # noqa: BLE001 - a bug on one recording fails that recording
            why = f"{type(exc).__name__}: {exc}".splitlines()[0][:200]
            msg = f"[E_INTERNAL] session {ref.key}, file {ref.name}: unexpected error ({why})"
            o, r = SessionOutcome(ref.key, ref.path, STATUS_FAILED, "E_INTERNAL", msg, [], ""), None
        outcomes.append(o)
        if r is not None:
            fitted.append(r)
    outcomes, fitted = drop_mixed_units(outcomes, fitted)
    unit_out = UnitOutcome(job.lot, job.unit, outcomes)
    diag_doc, note = None, None
    if fitted:
        reps = [o.calibration for o in outcomes if o.succeeded and o.calibration is not None]
        unit_out.calibration, unit_out.applied = field_unit_calibration(
            job.lot, job.unit, reps, [r.calibration for r in fitted]
        )
        unit_out.terms = unit_out.applied.terms
    else:
        unit_out.notes.append(f"unit {job.unit}: no field recording succeeded; no calibration produced")
    if run_discovery and fitted:
        best = max(range(len(fitted)), key=lambda i: len(fitted[i].pose_means))
        good = [o for o in outcomes if o.calibration is not None]
        name = good[best].calibration.provenance["recording"]
        if len(fitted[best].pose_means) < MIN_DISCOVERY_POSES:
            n = len(fitted[best].pose_means)
            note = f"model discovery skipped: {n} static poses, needs {MIN_DISCOVERY_POSES}"
        else:
            try:
                from calib_core.discovery.presentation import static_finding_rows
                from calib_core.discovery.static import diagnose_static

                diag = diagnose_static(fitted[best].calibration, fitted[best].pose_means, name)
                diag_doc = diag.to_dict()
                diag_doc["rows"] = static_finding_rows(diag, job.lot, job.unit)
            except Exception as exc:  # noqa: BLE001 - discovery must not cost the unit its calibration
                note = f"model discovery failed: {type(exc).__name__}: {exc}"
    return UnitResult(job.lot, job.unit, unit_out, diag_doc, note, time.perf_counter() - t0)


def add_field_units(
    dataset,
    store,
    force: bool,
    refs: list,
    jobs: list,
    skipped: list,
    path_errors: list,
    follow_symlinks: bool = False,
):
    """The nightly's plan with the dataset's field units added: ``jobs`` (sorted by lot and
    unit), ``skipped`` and ``path_errors`` extended. ``refs``: the turntable sessions found
    (a unit that has them is not calibrated from field recordings)."""
    field_jobs, field_skipped, errors = plan_field_units(
        dataset,
        store.fingerprints(),
        force,
        frozenset(r.key.unit for r in refs),
        follow_symlinks=follow_symlinks,
    )
    return (
        sorted([*jobs, *field_jobs], key=lambda j: (j.lot, j.unit)),
        [*skipped, *field_skipped],
        [*path_errors, *errors],
    )


def field_unit_job(dataset, unit: str, follow_symlinks: bool = False) -> FieldUnitJob | None:
    """The rerun job of ``unit`` when it is a field unit (its recordings found), else None."""
    jobs, _, _ = plan_field_units(dataset, {}, force=True, unit=unit, follow_symlinks=follow_symlinks)
    if not jobs:
        return None
    return FieldUnitJob(jobs[0].lot, unit, jobs[0].refs, "rerun")
