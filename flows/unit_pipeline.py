"""One session and one unit, from files to results: the plain-Python work that Prefect tasks
and the CLI both call. Never raises on bad data: a bad session becomes a failed outcome that
names its session, file, code and reason, and the rest of the unit goes on."""

from __future__ import annotations

import os
import time
import traceback
from dataclasses import replace

from calib_core.calibration import Calibration, TermValue
from calib_core.errors import DesignError
from calib_core.guards import NumericEvents
from calib_core.models.pipeline import calibrate_repetition, calibrate_repetitions, calibration_from_unit
from calib_core.results import UnitCalibration
from calib_core.steps import StepMeans
from calib_core.tables import ColumnTable
from flows.field_units import calibrate_field_unit_job
from flows.memory import keep_freed_memory
from flows.noise_units import apply_noise
from flows.unit_outcomes import (  # noqa: F401  (re-exported: the unit pipeline's results)
    STATUS_FAILED,
    STATUS_OK,
    STATUS_WARNED,
    SessionOutcome,
    UnitOutcome,
    UnitResult,
    failed_unit_result,
)
from schemas.averaging import leave_out_inconsistent_steps, numeric_warning, session_step_means
from schemas.dataset import SessionRef, read_session_files
from schemas.errors import SessionError, from_design_error
from schemas.hive import NOISE_DIR
from schemas.reader import read_session
from schemas.unit_noise import MAX_STATIC_SAMPLES, static_steps
from schemas.unit_plan import FIELD, TURNTABLE, UnitJob  # noqa: F401  (UnitJob re-exported)


def calibrate_session(ref: SessionRef, keep_step_means: bool = True) -> SessionOutcome:
    """Read, validate, average and fit one session."""
    return calibrate_sessions([ref], keep_step_means)[0]


def calibrate_sessions(
    refs: list[SessionRef], keep_step_means: bool = True, keep_static_steps: bool = False
) -> list[SessionOutcome]:
    """:func:`calibrate_session` of each session (the repetitions of a unit): every session
    read first, then the fits of those read together (``calibrate_repetitions`` stacks the
    sessions that share a step layout); each outcome is the one its session gives alone, but
    for the steps left out because they contradict the same step in the unit's other
    repetitions (``W_INCONSISTENT_STEP``, :func:`schemas.averaging.leave_out_inconsistent_steps`).
    ``keep_static_steps``: each outcome also keeps its session's static steps as read
    (:func:`schemas.unit_noise.static_steps`, what the noise model is measured on without a
    recording), from the first sessions until they hold ``MAX_STATIC_SAMPLES``."""
    fps = []
    read: list[tuple[int, StepMeans, list]] = []
    outcomes: list[SessionOutcome | None] = [None] * len(refs)
    static: list = [None] * len(refs)
    n_static = 0
    for i, ref in enumerate(refs):
        # one read of each file: the fingerprint is that of the very bytes calibrated
        files = read_session_files(ref.path)
        fps.append(files.fingerprint)
        try:
            data = read_session(ref, files)
            sm, warns = session_step_means(data)
        except Exception as exc:  # noqa: BLE001 - mapped to the session's failure below
            outcomes[i] = _failed(ref, fps[i], exc)
            continue
        if keep_static_steps and n_static < MAX_STATIC_SAMPLES:
            try:
                static[i] = static_steps(data)
                n_static += static[i].n_samples
            except Exception:  # noqa: BLE001 - the noise model then reads the session again
                static[i] = None
        data = files = None  # the samples are not held past their session
        read.append((i, sm, warns))
    # steps that contradict the unit's other repetitions are left out before the fits
    # (chamber sessions only against those of their own setpoint: the temperature moves them)
    checked: list = [None] * len(read)
    groups: dict = {}
    for k, (_, sm, _) in enumerate(read):
        groups.setdefault((sm.metadata or {}).get("chamber_setpoint_c"), []).append(k)
    for ks in groups.values():
        for k, item in zip(ks, leave_out_inconsistent_steps([read[k][1:] for k in ks])):
            checked[k] = item
    kept = []
    for (i, _, _), item in zip(read, checked):
        if isinstance(item, SessionError):  # too many steps lost in all
            outcomes[i] = _failed(refs[i], fps[i], item)
        else:
            kept.append((i, *item))
    read = kept
    fits, numeric = _fit_recording_numeric_events([sm for _, sm, _ in read])
    for (i, sm, warns), fit, events in zip(read, fits, numeric):
        ref, fp = refs[i], fps[i]
        if isinstance(fit, Exception):
            outcomes[i] = _failed(ref, fp, fit)
            continue
        if events:
            warns = [*warns, numeric_warning(str(ref.key), "fitting it", events)]
        warning_texts = [str(w) for w in warns] + list(fit.calibration.warnings)
        fit.calibration.warnings = warning_texts
        fit.calibration.provenance.update({"path": str(ref.path), "fingerprint": fp})
        status = STATUS_WARNED if warning_texts else STATUS_OK
        outcomes[i] = SessionOutcome(
            ref.key,
            ref.path,
            status,
            None,
            None,
            warning_texts,
            fp,
            fit.calibration,
            fit.residual_table,
            fit.compensation_table,
            sm if keep_step_means else None,
            list(fit.calibration.protocol_notes),
            static_steps=static[i],
        )
    return outcomes


def _fit_recording_numeric_events(sms: list[StepMeans]) -> tuple[list, list[NumericEvents]]:
    """``calibrate_repetitions(sms)`` and, per session, the floating-point errors NumPy met
    fitting it. The sessions are fitted together; only when that meets some are they fitted
    again one at a time (the same fits) to tell whose they are."""
    with NumericEvents() as together:
        fits = calibrate_repetitions(sms)
    if not together or len(sms) == 1:
        return fits, [together] * len(sms)
    fits, events = [], []
    for sm in sms:
        with NumericEvents() as alone:
            try:
                fits.append(calibrate_repetition(sm))
            except Exception as exc:  # noqa: BLE001 - the caller reports it for its session
                fits.append(exc)
        events.append(alone)
    return fits, events


def _failed(ref: SessionRef, fp: str, exc: Exception) -> SessionOutcome:
    """The failed outcome of a session whose reading or fitting raised ``exc``."""
    if isinstance(exc, SessionError):
        return SessionOutcome(ref.key, ref.path, STATUS_FAILED, exc.code, str(exc), [], fp)
    if isinstance(exc, DesignError):
        err = (
            from_design_error(exc, str(ref.key))
            if exc.code == "E_UNDETERMINED"
            else SessionError(exc.code, str(ref.key), "samples.parquet", exc.reason)
        )
        return SessionOutcome(ref.key, ref.path, STATUS_FAILED, err.code, str(err), [], fp)
    # a bug must not stop the fleet; it is reported with its trace
    tb = traceback.format_exception_only(type(exc), exc)[-1].strip()
    msg = f"[E_INTERNAL] session {ref.key}, path {ref.path}: unexpected error ({tb})"
    return SessionOutcome(ref.key, ref.path, STATUS_FAILED, "E_INTERNAL", msg, [], fp)


def aggregate_unit(
    lot: str,
    unit: str,
    outcomes: list[SessionOutcome],
    terms: tuple[TermValue, ...] = (),
    extended: Calibration | None = None,
) -> UnitOutcome:
    """Average the unit's successful repetitions into its calibration.

    ``extended`` is model discovery's calibration (K and biases re-estimated jointly with the
    terms it kept). When given with terms it is the one applied: adding terms on top of the
    xu2016 K would count twice what the xu2016 fit already absorbed of the effect (a cubic
    rate error partly moves k_g33)."""
    good = [o.calibration for o in outcomes if o.succeeded and o.calibration is not None]
    out = UnitOutcome(lot, unit, sorted(outcomes, key=lambda o: o.key.rep), terms=terms)
    if good:
        out.calibration = UnitCalibration.from_reps(lot, unit, good)
        if extended is not None and terms:
            out.applied = replace(
                extended,
                metadata={
                    **calibration_from_unit(out.calibration).metadata,
                    "model": "discovery (joint fit)",
                },
            )
        else:
            out.applied = calibration_from_unit(out.calibration, terms)
    else:
        out.notes.append(f"unit {unit}: no session succeeded; no calibration produced")
    return out


def calibrate_unit(refs: list[SessionRef], keep_step_means: bool = True) -> UnitOutcome:
    """All sessions of one unit, fitted together (as the nightly does), then their aggregate."""
    if not refs:
        raise ValueError("no sessions given")
    outcomes = calibrate_sessions(sorted(refs, key=lambda r: r.key.rep), keep_step_means)
    return aggregate_unit(refs[0].key.lot, refs[0].key.unit, outcomes)


def _discovery_available() -> bool:
    try:
        import calib_core.discovery  # noqa: F401

        return True
    except ImportError:
        return False


def _recorded_noise(job: UnitJob, outcomes: list[SessionOutcome]) -> tuple | None:
    """(UnitNoise, notes) of the unit's noise recordings (``lot=L/unit=U/noise/``) through
    its affine calibration, for model discovery's null; None without a readable recording
    (discovery then estimates the noise from the repetitions)."""
    from schemas.unit_noise import recording_noise

    if not job.refs or not os.path.lexists(job.refs[0].path.parent / NOISE_DIR):
        return None  # most units: no recording, no preliminary aggregate
    prelim = aggregate_unit(job.lot, job.unit, outcomes)
    if prelim.applied is None:
        return None
    noise, notes = recording_noise(
        job.refs[0].path.parent, job.lot, job.unit, prelim.applied, getattr(job, "follow_symlinks", False)
    )
    return None if noise is None else (noise, notes)


def calibrate_unit_job(job: UnitJob, run_discovery: bool = True) -> UnitResult:
    """Calibrate every session of one unit, run model discovery on the good ones, aggregate.
    Never raises on bad data (the unit pipeline turns it into failed sessions)."""
    from calib_core.models.pipeline import residual_table

    t0 = time.perf_counter()
    outcomes = calibrate_sessions(sorted(job.refs, key=lambda r: r.key.rep), keep_static_steps=True)
    diag_doc, note, terms, extended, evidence = None, None, (), None, None
    good_sm = [o.step_means for o in outcomes if o.succeeded and o.step_means is not None]
    recorded = None  # the unit's noise from its noise recordings, measured before discovery
    if run_discovery and _discovery_available() and len(good_sm) >= 2:
        from calib_core.discovery import diagnose_unit

        try:
            from calib_core.discovery.measured_noise import MeasuredNoise
            from calib_core.discovery.presentation import finding_rows

            try:  # a recording that cannot be measured leaves discovery its own estimate
                recorded = _recorded_noise(job, outcomes)
            except Exception as exc:  # noqa: BLE001
                note = f"noise recording not used by discovery: {type(exc).__name__}: {exc}"
            measured = (
                None
                if recorded is None
                else MeasuredNoise.from_document(recorded[0].model, recorded[0].source)
            )
            try:
                diag = diagnose_unit(good_sm, tables=False, measured_noise=measured)
            except ValueError as exc:  # DesignError included
                if measured is None:
                    raise
                # a recording's model discovery cannot use (e.g. a channel without noise)
                note = f"noise recording not used by discovery: {exc}"
                diag = diagnose_unit(good_sm, tables=False)
            diag_doc = diag.to_dict()
            diag_doc["rows"] = finding_rows(diag)  # the store's discovery rows
            evidence = diag.evidence if len(diag.evidence) else None
            terms = tuple(diag.terms)
            extended = diag.calibration if terms else None
            if terms:  # residuals of the extended model, for the before/after plots
                good = [o for o in outcomes if o.succeeded and o.step_means is not None]
                for o, cal in zip(good, diag.calibrations_after):
                    ext = residual_table(o.step_means, cal, model="extended")
                    o.residual_table = ColumnTable.concat([o.residual_table, ext])
        except Exception as exc:  # discovery must not cost the unit its calibration
            note = f"model discovery failed: {type(exc).__name__}: {exc}"
    elif run_discovery and not _discovery_available():
        note = "model discovery skipped: calib_core.discovery is not available"
    elif run_discovery:
        note = f"model discovery skipped: {len(good_sm)} good repetition(s), needs 2"
    try:
        unit_out = aggregate_unit(job.lot, job.unit, outcomes, terms=terms, extended=extended)
    except Exception as exc:  # a bug in aggregation must not stop the fleet
        unit_out = UnitOutcome(job.lot, job.unit, sorted(outcomes, key=lambda o: o.key.rep))
        unit_out.notes.append(f"E_INTERNAL: aggregating unit {job.unit} failed: {type(exc).__name__}: {exc}")
        note = "; ".join(filter(None, [note, unit_out.notes[-1]]))
    try:  # chamber sessions (chamber_setpoint_c): the calibration over temperature
        from flows.thermal_units import apply_thermal

        thermal_note = apply_thermal(unit_out, unit_out.sessions)
    except Exception as exc:  # noqa: BLE001 - the unit keeps its single-temperature calibration
        thermal_note = (
            f"E_INTERNAL: thermal calibration of unit {job.unit} failed: {type(exc).__name__}: {exc}"
        )
    if thermal_note:
        unit_out.notes.append(thermal_note)
        note = "; ".join(filter(None, [note, thermal_note]))
    try:  # the unit's noise model (lot=L/unit=U/noise/ or its static steps): flows.noise_units
        unit_dir = job.refs[0].path.parent if job.refs else None
        if recorded is not None and not terms:  # measured through the same affine calibration
            unit_out.noise, noise_note = recorded[0], "; ".join(recorded[1]) or None
        else:
            noise_note = apply_noise(unit_out, unit_dir, getattr(job, "follow_symlinks", False))
    except Exception as exc:  # noqa: BLE001 - the unit keeps its calibration without a noise model
        noise_note = f"E_INTERNAL: noise model of unit {job.unit} failed: {type(exc).__name__}: {exc}"
    if noise_note:
        unit_out.notes.append(noise_note)
        note = "; ".join(filter(None, [note, noise_note]))
    for o in unit_out.sessions:  # step means and static steps are not kept past this point
        o.step_means = None
        o.static_steps = None
    return UnitResult(
        job.lot, job.unit, unit_out, diag_doc, note, time.perf_counter() - t0, discovery_evidence=evidence
    )


def calibrate_batch(jobs: list[UnitJob], run_discovery: bool = True) -> list[UnitResult]:
    keep_freed_memory()  # once per process: discovery's arrays reuse the heap
    return [_isolated_unit_job(j, run_discovery) for j in jobs]


# the unit pipeline of each kind of reference (schemas.unit_plan.UnitJob.kind): a callable
# (job, run_discovery) -> UnitResult that never raises on bad data
UNIT_PIPELINES = {TURNTABLE: calibrate_unit_job, FIELD: calibrate_field_unit_job}


def _isolated_unit_job(job: UnitJob, run_discovery: bool) -> UnitResult:
    """The unit pipeline of the job's kind, with any exception it lets through (a bug)
    turned into the unit's failure: the rest of the batch and of the fleet goes on."""
    try:
        return UNIT_PIPELINES[job.kind](job, run_discovery)
    except Exception as exc:  # noqa: BLE001 - one unit never fails the flow
        return failed_unit_result(job.lot, job.unit, "calibrating", exc)
