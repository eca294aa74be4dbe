"""The results store's rows of one calibrated unit, and their write.

A unit's result (``flows.unit_pipeline.UnitResult``: its sessions' outcomes, the averaged
calibration, model discovery's rows and series, the navigation drift) becomes the rows of
the tables ``sessions``, ``parameters``, ``summary``, ``units``, ``residuals``,
``compensation``, ``discovery``, ``discovery_evidence`` and ``navigation``
(``schemas.store_tables`` declares their columns), plus its calibration file. The flows
call :func:`unit_store_rows` per unit and :func:`write_unit_tables` once per lot.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import pandas as pd

from calib_core.results import ParamSummary
from calib_core.tables import ColumnTable
from schemas.results_store import STORE_FORMAT_VERSION, ResultsStore, iso, parse_when


@dataclass
class StoreRows:
    """The rows a store write holds, gathered unit by unit."""

    sessions: list[dict] = field(default_factory=list)
    parameters: list[dict] = field(default_factory=list)
    summary: list[dict] = field(default_factory=list)
    units: list[dict] = field(default_factory=list)
    discovery: list[dict] = field(default_factory=list)
    discovery_evidence: list[pd.DataFrame] = field(default_factory=list)
    navigation: list[pd.DataFrame] = field(default_factory=list)
    ok_units: set[tuple[str, str]] = field(default_factory=set)
    stale_units: dict[tuple[str, str], str] = field(default_factory=dict)
    new_files: list[Path] = field(default_factory=list)
    new_files_referenced: bool = False  # the units table pointing to new_files is written

    def extend(self, other: StoreRows) -> None:
        for name in (
            "sessions",
            "parameters",
            "summary",
            "units",
            "discovery",
            "discovery_evidence",
            "navigation",
            "new_files",
        ):
            getattr(self, name).extend(getattr(other, name))
        self.ok_units |= other.ok_units
        self.stale_units.update(other.stale_units)


def remove_files(paths: list[Path]) -> None:
    for p in paths:
        try:
            p.unlink()
        except OSError:
            pass


def summary_row(lot: str, unit: str, ps: ParamSummary, run_id: str) -> dict[str, Any]:
    """A ``summary`` row of one parameter over a unit's repetitions, not yet judged (the
    re-flag of its lot sets the flag and lot columns)."""
    return {
        "lot": lot,
        "unit": unit,
        "model": ps.model,
        "parameter": ps.name,
        "mean": ps.mean,
        "std": ps.std,
        "min": ps.min,
        "max": ps.max,
        "n_reps": ps.n_reps,
        "stderr_of_mean": ps.stderr_of_mean,
        "unit_of_measure": ps.unit,
        "flagged": False,
        "flag_reason": "",
        "stale": False,
        "stale_reason": "",
        "run_id": run_id,
    }


def acquisition_time(session_starts) -> str | None:
    """The last of the sessions' ``session_start`` values (ISO 8601, UTC), None when none is
    readable: a calibration describes the unit as measured once its sessions are done."""
    from schemas.contract import session_start_problem

    times = []
    for v in session_starts:
        if isinstance(v, str) and v.strip() and session_start_problem(v) is None:
            try:
                times.append(parse_when(v))
            except ValueError:
                continue
    return iso(max(times)) if times else None


def calibration_file_extra(ur: Any, context: dict[str, Any]) -> dict[str, Any]:
    """The sections a unit's calibration file holds beside the applied calibration (the same
    for the results store and ``mimucal calibrate --json``): ``provenance`` (``context``:
    run id, code version, time..., then the sessions used and failed, the extension terms,
    model discovery's verdict), ``averaged`` (mean, std and units over the repetitions) and
    ``repetitions`` (each repetition's fits with standard errors). ``ur``: a unit's result
    (``flows.unit_pipeline.UnitResult``)."""
    from schemas.unit_document import calibration_file_sections

    out = ur.outcome
    failed = [
        {"rep": s.key.rep, "code": s.code, "message": s.message} for s in out.sessions if not s.succeeded
    ]
    used = [
        {
            "rep": s.key.rep,
            "path": str(s.path),
            "fingerprint": s.fingerprint,
            "status": s.status,
            "session_start": (s.calibration.provenance or {}).get("session_start") if s.calibration else None,
        }
        for s in out.sessions
        if s.succeeded
    ]
    # when the unit was measured (its sessions' last session_start; None when no session
    # says it: then the time of the calibration is when it was produced)
    context = {**context, "acquired_at": acquisition_time(u["session_start"] for u in used)}
    doc = calibration_file_sections(
        ur.lot,
        ur.unit,
        out.calibration.reps,
        failed,
        used,
        [t.name for t in out.applied.terms],
        ur.diagnosis,
        context,
    )
    noise = getattr(out, "noise", None)  # the measured noise model (flows.noise_units)
    if noise is not None:
        doc["noise"] = noise.to_dict()
    return doc


def unit_store_rows(
    store: ResultsStore,
    ur: Any,
    rows: StoreRows,
    prev_state: dict,
    run_id: str,
    code_version: str,
    when,
    stamp: str,
) -> None:
    """One unit's rows into ``rows``, and its calibration file (written last). ``ur``: the
    unit's result (``flows.unit_pipeline.UnitResult``); ``prev_state``: (lot, unit) -> its
    stored ``units`` row (a unit whose recalibration failed keeps its last calibration,
    marked stale)."""
    key = (ur.lot, ur.unit)
    out = ur.outcome
    for s in out.sessions:
        rows.sessions.append(
            {
                "lot": s.key.lot,
                "unit": s.key.unit,
                "rep": s.key.rep,
                "status": s.status,
                "error_code": s.code,
                "message": s.message,
                "warnings": list(s.warnings),
                # a unit that failed as a whole (E_INTERNAL) keeps no fingerprint: the next run
                # sees its sessions as changed and tries it again
                "fingerprint": None if ur.error_code else s.fingerprint,
                "run_id": run_id,
                "path": str(s.path),
                "calibrated_at": stamp,
                "protocol_notes": list(getattr(s, "protocol_notes", [])),
            }
        )
    base = {
        "lot": ur.lot,
        "unit": ur.unit,
        "n_sessions": len(out.sessions),
        "n_ok": sum(s.status == "ok" for s in out.sessions),
        "n_warned": sum(s.status == "warned" for s in out.sessions),
        "n_failed": sum(s.status == "failed" for s in out.sessions),
        "run_id": run_id,
        "updated_at": stamp,
        "error_code": ur.error_code,
    }
    if ur.calibrated:
        if ur.navigation is not None and len(ur.navigation):
            rows.navigation.append(ur.navigation.assign(lot=ur.lot, unit=ur.unit))
        for s in out.sessions:
            if s.calibration is None or not s.succeeded:
                continue
            for p in s.calibration.parameters():
                rows.parameters.append(
                    {
                        "lot": ur.lot,
                        "unit": ur.unit,
                        "rep": s.key.rep,
                        "model": p.model,
                        "parameter": p.name,
                        "value": p.value,
                        "stderr": p.stderr,
                        "unit_of_measure": p.unit,
                        "code_version": code_version,
                        "run_id": run_id,
                    }
                )
        rows.summary += [summary_row(ur.lot, ur.unit, ps, run_id) for ps in out.calibration.summary]
        extra = calibration_file_extra(
            ur,
            {
                "run_id": run_id,
                "code_version": code_version,
                "calibrated_at": stamp,
                "store_format_version": STORE_FORMAT_VERSION,
            },
        )
        acquired = extra["provenance"]["acquired_at"]
        discovery_rows(ur, rows, run_id)
        # numpy values and NaNs of the document are converted while writing (as jsonable()
        # would, without a second walk over the document); the file is written last, so a
        # unit that fails before it leaves no file
        path = store.save_calibration(out.applied, ur.unit, extra, when, jsonable=True)
        rows.new_files.append(path)
        rows.units.append(
            {
                **base,
                "state": "calibrated",
                "reason": "",
                "calibration_file": str(path.relative_to(store.root)),
                "calibrated_at": stamp,
                "acquired_at": acquired,
            }
        )
        rows.ok_units.add(key)
        return
    reasons = "; ".join(f"rep {s.key.rep}: {s.code}" for s in out.sessions if not s.succeeded) or (
        "no session" if ur.error is None else ""
    )
    why = f"recalibration failed in run {run_id} ({reasons or ur.error_code})"
    if ur.error:
        why += f": {ur.error}"
    prev = prev_state.get(key)
    if prev is not None and isinstance(prev.calibration_file, str) and prev.calibration_file:
        rows.stale_units[key] = why
        rows.units.append(
            {
                **base,
                "state": "stale",
                "reason": why,
                "calibration_file": prev.calibration_file,
                "calibrated_at": prev.calibrated_at,
                "acquired_at": getattr(prev, "acquired_at", None),
            }
        )
    else:
        rows.units.append(
            {**base, "state": "failed", "reason": why, "calibration_file": None, "calibrated_at": None}
        )
    discovery_rows(ur, rows, run_id)


def unit_row_from_calibration_file(
    unit: str, provenance: dict[str, Any], calibration_file: str, produced
) -> dict[str, Any]:
    """The ``units`` row of a unit rebuilt from its newest calibration file (``mimucal
    repair``): its provenance names the lot, run and sessions; ``produced`` is the file's
    time stamp (datetime)."""
    used = provenance.get("sessions_used") or []
    failed = provenance.get("sessions_failed") or []
    return {
        "lot": provenance.get("lot"),
        "unit": unit,
        "state": "calibrated",
        "reason": "rebuilt by 'mimucal repair' from the calibration file",
        "n_sessions": len(used) + len(failed),
        "n_ok": sum(1 for s in used if s.get("status") == "ok"),
        "n_warned": sum(1 for s in used if s.get("status") == "warned"),
        "n_failed": len(failed),
        "calibration_file": calibration_file,
        "calibrated_at": provenance.get("calibrated_at") or iso(produced),
        "run_id": provenance.get("run_id"),
        "updated_at": iso(produced),
        "flagged": False,
        "flag_reason": "",
    }


def discovery_rows(ur: Any, rows: StoreRows, run_id: str) -> None:
    """One row per finding, numbers as the report shows them
    (:func:`calib_core.discovery.presentation.finding_rows`), and the series behind each
    finding's figure."""
    if ur.diagnosis is None:
        return
    found = ur.diagnosis.get("rows") or [{"effect": None}]
    rows.discovery += [{**r, "lot": ur.lot, "unit": ur.unit, "run_id": run_id} for r in found]
    if ur.discovery_evidence is not None and len(ur.discovery_evidence):
        rows.discovery_evidence.append(ur.discovery_evidence.assign(run_id=run_id))


def session_tables_frame(results: list, attr: str) -> pd.DataFrame | None:
    """The per-session tables (``residual_table`` / ``compensation_table``) of the units'
    successful sessions as ONE DataFrame, lot, unit and rep inserted first: equal to
    concatenating the units' ``residuals_frame()`` / ``compensation_frame()``, without
    building a DataFrame per unit and concatenating them."""
    tables = [t for ur in results for t in ur.outcome.session_tables(attr)]
    if not tables:
        return None
    try:
        return ColumnTable.concat(tables).to_frame()
    except ValueError:  # columns differ between sessions: per unit, as UnitOutcome builds them
        frames = [
            f
            for f in (
                getattr(ur.outcome, "residuals_frame" if attr == "residual_table" else "compensation_frame")()
                for ur in results
            )
            if f is not None
        ]
        return pd.concat(frames, ignore_index=True) if frames else None


def _frame(rows: list[dict]) -> pd.DataFrame:
    return pd.DataFrame(rows) if rows else pd.DataFrame()


def write_unit_tables(store: ResultsStore, results: list, rows: StoreRows) -> None:
    """The tables' rows of the units ``results`` (gathered by :func:`unit_store_rows`): each
    table's rows of those units replaced, units whose recalibration failed keeping theirs
    (their summary marked stale in the same write)."""
    ok_units, stale_units = rows.ok_units, rows.stale_units
    all_units = {(ur.lot, ur.unit) for ur in results}
    store.replace_units("parameters", _frame(rows.parameters), ok_units)
    store.replace_units(
        "summary",
        _frame(rows.summary),
        ok_units,
        set_values={key: {"stale": True, "stale_reason": why} for key, why in stale_units.items()},
    )
    calibrated = [ur for ur in results if (ur.lot, ur.unit) in ok_units]
    for name, attr in (("residuals", "residual_table"), ("compensation", "compensation_table")):
        store.replace_units(name, session_tables_frame(calibrated, attr), ok_units)
    nav_units = {(ur.lot, ur.unit) for ur in results if ur.navigation is not None}
    if nav_units:
        store.replace_units(
            "navigation",
            pd.concat(rows.navigation, ignore_index=True) if rows.navigation else None,
            nav_units,
        )
    disc_units = {(ur.lot, ur.unit) for ur in results if ur.diagnosis is not None}
    if disc_units:
        store.replace_units("discovery", _frame(rows.discovery), disc_units)
        store.replace_units(
            "discovery_evidence",
            pd.concat(rows.discovery_evidence, ignore_index=True) if rows.discovery_evidence else None,
            disc_units,
        )
    from schemas.store_noise import write_noise_tables  # the noise and noise_allan tables

    write_noise_tables(store, calibrated, next((r["run_id"] for r in rows.units), None))
    # the units table next to last: until it is written no table points to the new
    # calibration files, so a failure before it may remove them (flows.nightly.store_results)
    store.replace_units("units", _frame(rows.units), all_units)
    rows.new_files_referenced = True
    # sessions.parquet last: its fingerprints tell the next run which units are done, so a
    # crash before this point leaves the units "changed" and the rerun redoes them whole
    store.replace_units("sessions", _frame(rows.sessions), all_units)
