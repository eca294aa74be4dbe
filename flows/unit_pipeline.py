"""One session and one unit, from files to results: the plain-Python work that Prefect tasks
and the CLI both call. Never raises on bad data: a bad session becomes a failed outcome that
names its session, file, code and reason, and the rest of the unit goes on."""
from __future__ import annotations

import traceback
from dataclasses import dataclass, field, replace
from pathlib import Path

import pandas as pd

from calib_core.calibration import Calibration, TermValue
from calib_core.errors import DesignError
from calib_core.pipeline import calibrate_repetition, calibration_from_unit
from calib_core.results import Param, RepetitionCalibration, UnitCalibration
from calib_core.steps import SessionKey, StepMeans
from schemas.averaging import read_step_means
from schemas.dataset import SessionRef, fingerprint
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
    residuals: pd.DataFrame | None = None
    compensation: pd.DataFrame | None = None
    step_means: StepMeans | None = None  # kept for discovery; dropped before storing

    @property
    def succeeded(self) -> bool:
        return self.status != STATUS_FAILED


def calibrate_session(ref: SessionRef, keep_step_means: bool = True) -> SessionOutcome:
    """Read, validate, average and fit one session."""
    fp = _safe_fingerprint(ref.path)
    try:
        sm, warns = read_step_means(ref)
        fit = calibrate_repetition(sm)
    except SessionError as exc:
        return SessionOutcome(ref.key, ref.path, STATUS_FAILED, exc.code, str(exc), [], fp)
    except DesignError as exc:
        err = (from_design_error(exc, str(ref.key)) if exc.code == "E_UNDETERMINED"
               else SessionError(exc.code, str(ref.key), "samples.parquet", exc.reason))
        return SessionOutcome(ref.key, ref.path, STATUS_FAILED, err.code, str(err), [], fp)
    except Exception as exc:  # a bug must not stop the fleet; it is reported with its trace
        tb = traceback.format_exception_only(type(exc), exc)[-1].strip()
        msg = f"[E_INTERNAL] session {ref.key}, path {ref.path}: unexpected error ({tb})"
        return SessionOutcome(ref.key, ref.path, STATUS_FAILED, "E_INTERNAL", msg, [], fp)
    warning_texts = [str(w) for w in warns] + list(fit.calibration.warnings)
    fit.calibration.warnings = warning_texts
    fit.calibration.provenance.update({"path": str(ref.path), "fingerprint": fp})
    status = STATUS_WARNED if warning_texts else STATUS_OK
    return SessionOutcome(ref.key, ref.path, status, None, None, warning_texts, fp,
                          fit.calibration, fit.residuals, fit.compensation,
                          sm if keep_step_means else None)


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

    @property
    def parameter_rows(self) -> list[Param]:
        return [p for s in self.sessions if s.calibration for p in s.calibration.parameters()]


def aggregate_unit(lot: str, unit: str, outcomes: list[SessionOutcome],
                   terms: tuple[TermValue, ...] = (), extended: Calibration | None = None
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
            out.applied = replace(extended, metadata={
                **calibration_from_unit(out.calibration).metadata, "model": "discovery (joint fit)"})
        else:
            out.applied = calibration_from_unit(out.calibration, terms)
    else:
        out.notes.append(f"unit {unit}: no session succeeded; no calibration produced")
    return out


def calibrate_unit(refs: list[SessionRef], keep_step_means: bool = True) -> UnitOutcome:
    """All sessions of one unit, then their aggregate."""
    if not refs:
        raise ValueError("no sessions given")
    outcomes = [calibrate_session(r, keep_step_means) for r in refs]
    return aggregate_unit(refs[0].key.lot, refs[0].key.unit, outcomes)
