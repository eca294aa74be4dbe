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

import time
from dataclasses import dataclass
from typing import Any

import numpy as np

from calib_core.models.field.discovery_choice import recording_for_discovery
from calib_core.models.field.results import field_unit_calibration
from flows.unit_outcomes import (
    STATUS_FAILED,
    STATUS_OK,
    STATUS_WARNED,
    SessionOutcome,
    UnitOutcome,
    UnitResult,
)
from schemas.errors import E_IMPLAUSIBLE, E_MIXED_UNITS
from schemas.field_dataset import FieldRecordingRef, field_fingerprint
from schemas.field_options import clip_limit, init_static_s, starting_scales
from schemas.unit_plan import FIELD, UnitJob, plan_field_units


def field_fit_problems(gyro, accel, figures, move_ok) -> list:
    """:func:`calib_core.guards.check_field_fit` on a fitted recording (its affine gyro and
    accel fits and its figures after the fit): what makes it no working sensor's."""
    from calib_core.guards import check_field_fit

    s = figures.summary("", move_ok)
    return check_field_fit(s["norm_rms_mg"], s["angle_rms_deg"], gyro.K, gyro.w0, accel.K, accel.f0)


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
        move_ok = usable_moves(rec.gyro, det.poses, clipped_samples(rec.gyro, clip_limit(o)))
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
        best, note = recording_for_discovery([len(r.pose_means) for r in fitted])
        good = [o for o in outcomes if o.calibration is not None]
        if best is not None:
            name = good[best].calibration.provenance["recording"]
            try:
                from calib_core.discovery.presentation import static_finding_rows
                from calib_core.discovery.static import diagnose_static

                diag = diagnose_static(fitted[best].calibration, fitted[best].pose_means, name)
                diag_doc = diag.to_dict()
                diag_doc["rows"] = static_finding_rows(diag, job.lot, job.unit)
            except Exception as exc:  # noqa: BLE001 - discovery must not cost the unit its calibration
                note = f"model discovery failed: {type(exc).__name__}: {exc}"
    return UnitResult(job.lot, job.unit, unit_out, diag_doc, note, time.perf_counter() - t0)


def field_unit_job(dataset, unit: str, follow_symlinks: bool = False) -> UnitJob | None:
    """The rerun job of ``unit`` when it is a field unit (its recordings found), else None."""
    jobs, _, _ = plan_field_units(dataset, {}, force=True, unit=unit, follow_symlinks=follow_symlinks)
    if not jobs:
        return None
    return UnitJob(jobs[0].lot, unit, jobs[0].refs, "rerun", FIELD)
