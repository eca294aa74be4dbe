"""One session and one unit, from files to results: the plain-Python work that Prefect tasks
and the CLI both call. Never raises on bad data: a bad session becomes a failed outcome that
names its session, file, code and reason, and the rest of the unit goes on."""

from __future__ import annotations

import time
import traceback
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import pandas as pd

from calib_core.calibration import Calibration, TermValue
from calib_core.errors import DesignError
from calib_core.guards import NumericEvents
from calib_core.models.pipeline import calibrate_repetition, calibrate_repetitions, calibration_from_unit
from calib_core.results import RepetitionCalibration, UnitCalibration
from calib_core.steps import SessionKey, StepMeans
from calib_core.tables import ColumnTable
from schemas.averaging import leave_out_inconsistent_steps, numeric_warning, read_step_means
from schemas.dataset import SessionRef, UnitJob, fingerprint  # noqa: F401  (UnitJob re-exported)
from schemas.errors import SessionError, from_design_error

STATUS_OK, STATUS_WARNED, STATUS_FAILED = "ok", "warned", "failed"


@dataclass
class SessionOutcome:
    key: SessionKey
    path: Path
    status: str
    code: str | None
    message: str | None
    warnings: list[str]
    fingerprint: str
    calibration: RepetitionCalibration | None = None
    # the session's tables as numpy columns: the unit builds one DataFrame of all its
    # sessions (UnitOutcome.residuals_frame / compensation_frame), not one per session
    residual_table: ColumnTable | None = None
    compensation_table: ColumnTable | None = None
    step_means: StepMeans | None = None  # kept for discovery; dropped before storing
    # facts about the protocol (P_...), not warnings: said once per lot, the session stays ok
    protocol_notes: list[str] = field(default_factory=list)

    @property
    def succeeded(self) -> bool:
        return self.status != STATUS_FAILED

    @property
    def residuals(self) -> pd.DataFrame | None:
        """This session's residual rows as a DataFrame (built on each call)."""
        return None if self.residual_table is None else self.residual_table.to_frame()

    @property
    def compensation(self) -> pd.DataFrame | None:
        return None if self.compensation_table is None else self.compensation_table.to_frame()


def calibrate_session(ref: SessionRef, keep_step_means: bool = True) -> SessionOutcome:
    """Read, validate, average and fit one session."""
    return calibrate_sessions([ref], keep_step_means)[0]


def calibrate_sessions(refs: list[SessionRef], keep_step_means: bool = True) -> list[SessionOutcome]:
    """:func:`calibrate_session` of each session (the repetitions of a unit): every session
    read first, then the fits of those read together (``calibrate_repetitions`` stacks the
    sessions that share a step layout); each outcome is the one its session gives alone, but
    for the steps left out because they contradict the same step in the unit's other
    repetitions (``W_INCONSISTENT_STEP``, :func:`schemas.averaging.leave_out_inconsistent_steps`)."""
    fps = []
    read: list[tuple[int, StepMeans, list]] = []
    outcomes: list[SessionOutcome | None] = [None] * len(refs)
    for i, ref in enumerate(refs):
        fps.append(_safe_fingerprint(ref.path))
        try:
            sm, warns = read_step_means(ref)
        except Exception as exc:  # noqa: BLE001 - mapped to the session's failure below
            outcomes[i] = _failed(ref, fps[i], exc)
            continue
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


def _safe_fingerprint(path: Path) -> str:
    try:
        return fingerprint(path)
    except OSError:
        return ""


@dataclass
class UnitOutcome:
    lot: str
    unit: str
    sessions: list[SessionOutcome]
    calibration: UnitCalibration | None = None
    applied: Calibration | None = None
    terms: tuple[TermValue, ...] = ()
    diagnosis: object | None = None  # calib_core.discovery.Diagnosis when discovery ran
    notes: list[str] = field(default_factory=list)
    noise: Any = None  # calib_core.noise_fleet.UnitNoise: the measured noise (flows.noise_units)

    def residuals_frame(self) -> pd.DataFrame | None:
        """The per-step residual rows of every successful session, one frame for the unit
        (columns ``calib_core.models.pipeline.RESIDUAL_COLUMNS``), or None when there is none."""
        return self._table("residual_table")

    def compensation_frame(self) -> pd.DataFrame | None:
        """The xu2016 Table 3 rows of every successful session, one frame for the unit."""
        return self._table("compensation_table")

    def _table(self, attr: str) -> pd.DataFrame | None:
        tables = self.session_tables(attr)
        return ColumnTable.concat(tables).to_frame() if tables else None

    def session_tables(self, attr: str) -> list[ColumnTable]:
        """The successful sessions' ``attr`` tables (``residual_table`` /
        ``compensation_table``), each with lot, unit and rep as its leading columns."""
        tables = []
        for s in self.sessions:
            t = getattr(s, attr)
            if s.succeeded and s.calibration is not None and t is not None and len(t):
                for c, v in (("lot", self.lot), ("unit", self.unit), ("rep", s.key.rep)):
                    if c not in t.columns:  # each inserted first, as DataFrame.insert(0, ...)
                        t = t.with_leading(c, v)
                tables.append(t)
        return tables


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


# --- one unit as the nightly and rerun flows run it (discovery included) ---------------------
@dataclass
class UnitResult:
    """What a task returns for one unit: the lead's UnitOutcome (step means dropped) plus
    discovery."""

    lot: str
    unit: str
    outcome: Any  # flows.unit_pipeline.UnitOutcome
    diagnosis: dict | None = None
    discovery_note: str | None = None
    elapsed_s: float = 0.0
    navigation: pd.DataFrame | None = None  # zhang2017 drift curves (reruns only)
    discovery_evidence: pd.DataFrame | None = None  # the series behind discovery's figures
    # a unit-level failure (an exception in its calibration, discovery or storage): its code
    # (E_INTERNAL) and one-line message; the unit keeps its last good calibration
    error_code: str | None = None
    error: str | None = None

    @property
    def calibrated(self) -> bool:
        return self.outcome is not None and self.outcome.applied is not None

    @property
    def n_failed(self) -> int:
        return sum(1 for s in self.outcome.sessions if s.status == "failed")


def _discovery_available() -> bool:
    try:
        import calib_core.discovery  # noqa: F401

        return True
    except ImportError:
        return False


def calibrate_unit_job(job: UnitJob, run_discovery: bool = True) -> UnitResult:
    """Calibrate every session of one unit, run model discovery on the good ones, aggregate.
    Never raises on bad data (the unit pipeline turns it into failed sessions)."""
    from calib_core.models.pipeline import residual_table
    from flows.unit_pipeline import aggregate_unit, calibrate_sessions

    t0 = time.perf_counter()
    outcomes = calibrate_sessions(sorted(job.refs, key=lambda r: r.key.rep))
    diag_doc, note, terms, extended, evidence = None, None, (), None, None
    good_sm = [o.step_means for o in outcomes if o.succeeded and o.step_means is not None]
    if run_discovery and _discovery_available() and len(good_sm) >= 2:
        from calib_core.discovery import diagnose_unit

        try:
            from calib_core.discovery.presentation import finding_rows

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
        from flows.unit_pipeline import UnitOutcome

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
        from flows.noise_units import apply_noise

        unit_dir = job.refs[0].path.parent if job.refs else None
        noise_note = apply_noise(unit_out, unit_dir, getattr(job, "follow_symlinks", False))
    except Exception as exc:  # noqa: BLE001 - the unit keeps its calibration without a noise model
        noise_note = f"E_INTERNAL: noise model of unit {job.unit} failed: {type(exc).__name__}: {exc}"
    if noise_note:
        unit_out.notes.append(noise_note)
        note = "; ".join(filter(None, [note, noise_note]))
    for o in unit_out.sessions:  # step means are not kept past this point
        o.step_means = None
    return UnitResult(
        job.lot, job.unit, unit_out, diag_doc, note, time.perf_counter() - t0, discovery_evidence=evidence
    )


def calibrate_batch(jobs: list[UnitJob], run_discovery: bool = True) -> list[UnitResult]:
    return [_isolated_unit_job(j, run_discovery) for j in jobs]


def _isolated_unit_job(job: UnitJob, run_discovery: bool) -> UnitResult:
    """:func:`calibrate_unit_job`, with any exception it lets through (a bug) turned into
    the unit's failure: the rest of the batch and of the fleet goes on."""
    try:
        from flows.field_units import FieldUnitJob, calibrate_field_unit_job

        if isinstance(job, FieldUnitJob):  # a unit of field recordings
            return calibrate_field_unit_job(job, run_discovery)
        return calibrate_unit_job(job, run_discovery)
    except Exception as exc:  # noqa: BLE001 - one unit never fails the flow
        return failed_unit_result(job.lot, job.unit, "calibrating", exc)


def failed_unit_result(
    lot: str, unit: str, doing: str, exc: BaseException, outcome: UnitOutcome | None = None
) -> UnitResult:
    """The E_INTERNAL result of a unit whose work raised ``exc`` while ``doing`` it; its
    sessions (when known) are kept, its calibration is not."""
    why = traceback.format_exception_only(type(exc), exc)[-1].strip()
    msg = f"[E_INTERNAL] unit {lot}/{unit}: unexpected error while {doing} ({why})"
    sessions = outcome.sessions if outcome is not None else []
    out = UnitOutcome(lot, unit, sessions, notes=[msg])
    return UnitResult(lot, unit, out, error_code="E_INTERNAL", error=msg)
