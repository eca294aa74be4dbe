"""What the unit pipelines give back, whatever the unit's reference (turntable sessions or
field recordings): a session's outcome, a unit's outcome (its sessions aggregated), and the
result a task returns for one unit. Shared by :mod:`flows.unit_pipeline` and
:mod:`flows.field_units`, which import it and not each other's results."""

from __future__ import annotations

import traceback
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import pandas as pd

from calib_core.calibration import Calibration, TermValue
from calib_core.results import RepetitionCalibration, UnitCalibration
from calib_core.steps import SessionKey, StepMeans
from calib_core.tables import ColumnTable

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
    # the static steps' samples as read (schemas.unit_noise.StaticSteps), kept for the unit's
    # noise model; dropped before storing
    static_steps: Any = None

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


@dataclass
class UnitResult:
    """What a task returns for one unit: the lead's UnitOutcome (step means dropped) plus
    discovery."""

    lot: str
    unit: str
    outcome: Any  # UnitOutcome
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
