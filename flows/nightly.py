"""Prefect flows: the nightly fleet calibration, the lot report rebuild and the single-unit
rerun. Orchestration only: the work is :mod:`flows.unit_pipeline` (per session/unit),
:mod:`calib_core.discovery`, :mod:`calib_core.outliers`, :mod:`schemas.results_store` and
:mod:`reports`.

Granularity: one Prefect task per *batch of units* (``batch_size`` units, default 8): a task
costs ~4 ms with the thread pool and ~60-85 ms with a process pool or Dask (docs/flows.md),
a session ~0.1-0.3 s. Tasks receive session paths, never arrays, and return fitted results
in memory (``persist_result=False``, no cache policy): Prefect writes no sample data.

The public functions ``nightly_fleet_calibration``, ``lot_quality_report`` and
``rerun_unit`` pick the task runner (thread pool of 2, or Dask at ``dask_address``), switch the
heartbeat off and call the flows.
"""

from __future__ import annotations

import json
import os
import sys
import time
import uuid
from collections import Counter, deque
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from flows import runtime

runtime.ensure_environment()

import numpy as np  # noqa: E402
import pandas as pd  # noqa: E402
from prefect import flow, get_run_logger, task  # noqa: E402
from prefect.cache_policies import NO_CACHE  # noqa: E402
from prefect.futures import as_completed  # noqa: E402

from calib_core.outliers import (  # noqa: E402
    KIND_LIMIT,
    LotFlags,
    OutlierConfig,
    apply_flags,
    flag_lots,
    known_thresholds,
    pooled_scales,
    pooling_rows,
    remember_thresholds,
)
from calib_core.tables import ColumnTable  # noqa: E402
from flows.compute_pool import run_in_pool  # noqa: E402
from flows.memory import release_memory  # noqa: E402
from flows.task_runners import (  # noqa: E402,F401
    DASK_ENV,
    DASK_TASK_THREADS,
    LOCAL_WORKERS,
    default_task_runner,
    make_task_runner,
    prestart_unit_work_pool,
    resolve_kind,
    unit_work_pool,
    uses_unit_work_pool,
)
from flows.unit_pipeline import (  # noqa: E402,F401  (re-exported: tests and tools import them here)
    UnitJob,
    UnitResult,
    _discovery_available,
    calibrate_batch,
    calibrate_unit_job,
    calibration_file_extra,
)
from schemas.dataset import DigestCache, SessionRef, find_sessions  # noqa: E402
from schemas.limits import config_from_toml  # noqa: E402
from schemas.results_store import (  # noqa: E402
    STORE_FORMAT_VERSION,
    ResultsStore,
    iso,
    jsonable,
    utc_now,
)

DEFAULT_BATCH_SIZE = 8


# --- plain-Python pieces (tested without Prefect) ------------------------------------------------
def plan_units(
    refs: list[SessionRef], previous: dict[tuple[str, str, int], str], force: bool = False, cache=None
) -> tuple[list[UnitJob], list[tuple[str, str]]]:
    """Units to calibrate (new, changed, or all with ``force``) and units skipped because
    every session's fingerprint (a content hash, schemas.dataset.fingerprint) is unchanged
    and no session appeared or disappeared. ``cache``: a schemas.dataset.DigestCache."""
    from schemas.dataset import fingerprint

    by_unit: dict[tuple[str, str], list[SessionRef]] = {}
    for r in refs:
        by_unit.setdefault((r.key.lot, r.key.unit), []).append(r)
    prev_reps: dict[tuple[str, str], set[int]] = {}
    for lot, unit, rep in previous:
        prev_reps.setdefault((lot, unit), set()).add(rep)
    jobs, skipped = [], []
    for (lot, unit), rs in sorted(by_unit.items()):
        if force:
            jobs.append(UnitJob(lot, unit, rs, "forced"))
            continue
        if (lot, unit) not in prev_reps:
            jobs.append(UnitJob(lot, unit, rs, "new"))
            continue
        reps_now = {r.key.rep for r in rs}
        changed = [
            r.key.rep for r in rs if previous.get((lot, unit, r.key.rep)) != fingerprint(r.path, cache)
        ]
        if changed or reps_now != prev_reps[(lot, unit)]:
            why = []
            if changed:
                why.append("changed rep " + ",".join(map(str, changed)))
            if reps_now - prev_reps[(lot, unit)]:
                why.append("new rep " + ",".join(map(str, sorted(reps_now - prev_reps[(lot, unit)]))))
            if prev_reps[(lot, unit)] - reps_now:
                why.append("removed rep " + ",".join(map(str, sorted(prev_reps[(lot, unit)] - reps_now))))
            jobs.append(UnitJob(lot, unit, rs, "; ".join(why)))
        else:
            skipped.append((lot, unit))
    return jobs, skipped


def _frame(rows: list[dict], name: str) -> pd.DataFrame:  # noqa: ARG001 (name: for reading)
    return pd.DataFrame(rows) if rows else pd.DataFrame()


def _session_rows(results: list[UnitResult], attr: str) -> pd.DataFrame | None:
    """The per-session tables (``residual_table`` / ``compensation_table``) of the units'
    successful sessions as ONE DataFrame, lot, unit and rep inserted first: equal to
    concatenating the units' ``residuals_frame()`` / ``compensation_frame()``, without
    building a DataFrame per unit (~1 ms each plus the concatenation)."""
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


def store_results(
    store: ResultsStore, results: list[UnitResult], run_id: str, code_version: str, when=None
) -> dict[str, Any]:
    """Write the units' rows (replacing only those units), their calibration files, and mark
    units whose recalibration failed as stale (keeping their last good results).

    One unit's failure here (an exception while building its rows or writing its calibration
    file) marks that unit failed with ``E_INTERNAL`` and the others are stored; a failure of
    the table writes (disk full, read-only store) removes the calibration files this call
    wrote while no table points at them yet (the units table is written next to last) and
    is raised: a run that fails before its units table adds no calibration."""
    when = when or utc_now()
    stamp = iso(when)
    rows = _StoreRows()
    previous_units = store.read(
        "units",
        lots={ur.lot for ur in results},
        columns=["lot", "unit", "calibration_file", "calibrated_at", "acquired_at"],
    )
    prev_state = {(r.lot, r.unit): r for r in previous_units.itertuples()}
    for i, ur in enumerate(results):
        unit_rows = _StoreRows()
        try:
            _unit_store_rows(store, ur, unit_rows, prev_state, run_id, code_version, when, stamp)
        except Exception as exc:  # noqa: BLE001 - one unit never fails the flow
            from flows.unit_pipeline import failed_unit_result

            if unit_rows.new_files:
                _remove_files(unit_rows.new_files)
            failed = failed_unit_result(ur.lot, ur.unit, "storing its results", exc, ur.outcome)
            failed.diagnosis, failed.discovery_note = None, ur.discovery_note
            results[i] = ur = failed
            unit_rows = _StoreRows()
            _unit_store_rows(store, ur, unit_rows, prev_state, run_id, code_version, when, stamp)
        rows.extend(unit_rows)
    try:
        _write_unit_tables(store, results, rows)
    except BaseException:
        if not rows.new_files_referenced:  # no table points to them: the run added nothing
            _remove_files(rows.new_files)
        raise
    return {
        "calibrated": sorted(f"{lot}/{u}" for lot, u in rows.ok_units),
        "stale": {f"{lot}/{u}": w for (lot, u), w in rows.stale_units.items()},
    }


@dataclass
class _StoreRows:
    """The rows :func:`store_results` writes, gathered unit by unit."""

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

    def extend(self, other: _StoreRows) -> None:
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


def _remove_files(paths: list[Path]) -> None:
    for p in paths:
        try:
            p.unlink()
        except OSError:
            pass


def _unit_store_rows(
    store: ResultsStore,
    ur: UnitResult,
    rows: _StoreRows,
    prev_state: dict,
    run_id: str,
    code_version: str,
    when,
    stamp: str,
) -> None:
    """One unit's rows into ``rows``, and its calibration file (written last)."""
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
            }
        )
    n_ok = sum(s.status == "ok" for s in out.sessions)
    n_warned = sum(s.status == "warned" for s in out.sessions)
    n_failed = sum(s.status == "failed" for s in out.sessions)
    base = {
        "lot": ur.lot,
        "unit": ur.unit,
        "n_sessions": len(out.sessions),
        "n_ok": n_ok,
        "n_warned": n_warned,
        "n_failed": n_failed,
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
        for ps in out.calibration.summary:
            rows.summary.append(
                {
                    "lot": ur.lot,
                    "unit": ur.unit,
                    "model": ps.model,
                    "parameter": ps.name,
                    "mean": ps.mean,
                    "std": ps.std,
                    "min": ps.min,
                    "max": ps.max,
                    "n_reps": ps.n_reps,
                    "unit_of_measure": ps.unit,
                    "flagged": False,
                    "flag_reason": "",
                    "stale": False,
                    "stale_reason": "",
                    "run_id": run_id,
                }
            )
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
        _discovery_rows(ur, rows, run_id)
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
    _discovery_rows(ur, rows, run_id)


def _discovery_rows(ur: UnitResult, rows: _StoreRows, run_id: str) -> None:
    """One row per finding, numbers as the report shows them
    (:func:`calib_core.discovery.presentation.finding_rows`), and the series behind each
    finding's figure."""
    if ur.diagnosis is None:
        return
    found = ur.diagnosis.get("rows") or [{"effect": None}]
    rows.discovery += [{**r, "lot": ur.lot, "unit": ur.unit, "run_id": run_id} for r in found]
    if ur.discovery_evidence is not None and len(ur.discovery_evidence):
        rows.discovery_evidence.append(ur.discovery_evidence.assign(run_id=run_id))


def _write_unit_tables(store: ResultsStore, results: list[UnitResult], rows: _StoreRows) -> None:
    """The tables' rows of ``results`` (gathered by :func:`store_results`)."""
    ok_units, stale_units = rows.ok_units, rows.stale_units
    all_units = {(ur.lot, ur.unit) for ur in results}
    store.replace_units("parameters", _frame(rows.parameters, "parameters"), ok_units)
    # units whose recalibration failed keep their rows, marked stale in the same write
    store.replace_units(
        "summary",
        _frame(rows.summary, "summary"),
        ok_units,
        set_values={key: {"stale": True, "stale_reason": why} for key, why in stale_units.items()},
    )
    calibrated = [ur for ur in results if (ur.lot, ur.unit) in ok_units]
    for name, attr in (("residuals", "residual_table"), ("compensation", "compensation_table")):
        store.replace_units(name, _session_rows(calibrated, attr), ok_units)
    nav_units = {(ur.lot, ur.unit) for ur in results if ur.navigation is not None}
    if nav_units:
        store.replace_units(
            "navigation",
            pd.concat(rows.navigation, ignore_index=True) if rows.navigation else None,
            nav_units,
        )
    disc_units = {(ur.lot, ur.unit) for ur in results if ur.diagnosis is not None}
    if disc_units:
        store.replace_units("discovery", _frame(rows.discovery, "discovery"), disc_units)
        store.replace_units(
            "discovery_evidence",
            pd.concat(rows.discovery_evidence, ignore_index=True) if rows.discovery_evidence else None,
            disc_units,
        )
    # the units table next to last: until it is written no table points to the new
    # calibration files, so a failure before it may remove them (store_results)
    store.replace_units("units", _frame(rows.units, "units"), all_units)
    rows.new_files_referenced = True
    # sessions.parquet last: its fingerprints tell the next run which units are done, so a
    # crash before this point leaves the units "changed" and the rerun redoes them whole
    store.replace_units("sessions", _frame(rows.sessions, "sessions"), all_units)


@dataclass
class RunTally:
    """What the run log needs of the units once their results are stored and dropped: the
    nightly flow stores lot by lot and keeps only this (memory bounded by one lot)."""

    calibrated: list[str] = field(default_factory=list)
    stale: dict[tuple[str, str], str] = field(default_factory=dict)
    failed_units: list[str] = field(default_factory=list)
    unit_errors: list[dict[str, str]] = field(default_factory=list)
    sessions_calibrated: int = 0
    failed_sessions: list[tuple[tuple, dict[str, Any]]] = field(default_factory=list)
    discovery_notes: set[str] = field(default_factory=set)
    lots: set[str] = field(default_factory=set)

    def add(self, results: list[UnitResult], stored: dict[str, Any]) -> None:
        self.calibrated.extend(stored["calibrated"])
        for r in results:  # keyed by (lot, unit): the order the units were sorted in
            name = f"{r.lot}/{r.unit}"
            if name in stored["stale"]:
                self.stale[(r.lot, r.unit)] = stored["stale"][name]
        self.lots.update(r.lot for r in results)
        self.failed_units.extend(f"{r.lot}/{r.unit}" for r in results if not r.calibrated)
        self.unit_errors.extend(
            {"unit": f"{r.lot}/{r.unit}", "code": r.error_code, "message": r.error}
            for r in results
            if r.error_code
        )
        self.sessions_calibrated += sum(
            1 for r in results for s in r.outcome.sessions if s.status != "failed"
        )
        self.failed_sessions.extend(
            ((r.lot, r.unit, i), {"session": str(s.key), "code": s.code, "message": s.message})
            for r in results
            for i, s in enumerate(r.outcome.sessions)
            if s.status == "failed"
        )
        self.discovery_notes.update(r.discovery_note for r in results if r.discovery_note)

    def log_fields(self) -> dict[str, Any]:
        # sorted as the run log had them when every unit was stored at once
        return {
            "units_calibrated": len(self.calibrated),
            "units_stale": {f"{lot}/{u}": self.stale[(lot, u)] for lot, u in sorted(self.stale)},
            "units_failed": sorted(self.failed_units),
            "unit_errors": sorted(self.unit_errors, key=lambda e: e["unit"]),
            "sessions_calibrated": self.sessions_calibrated,
            "failed_sessions": [f for _, f in sorted(self.failed_sessions, key=lambda x: x[0])],
        }


CLEAR_CONFIG = "none"  # ``--config none``: forget the stored configuration, use the defaults


def load_config(path: str | Path | None) -> OutlierConfig:
    if not path or str(path) == CLEAR_CONFIG:
        return OutlierConfig()
    p = Path(path)
    try:
        text = p.read_text()
    except OSError as exc:
        raise FileNotFoundError(f"outlier configuration {p}: {exc.strerror}") from None
    return config_from_toml(text, source=str(p))


def resolve_config(store: ResultsStore, path: str | Path | None) -> tuple[OutlierConfig, str | None | bool]:
    """The QA configuration of a run and what to store under the lock: ``--config FILE``
    sets it for this and every later run (returned text), ``--config none`` clears it
    (None), no ``--config`` keeps the one stored (False: nothing to store). A stored text
    that no longer parses is an error naming the file."""
    if path is None:
        text = store.read_qa_config()
        if text is None:
            return OutlierConfig(), False
        return config_from_toml(text, source=str(store.qa_config_path)), False
    if str(path) == CLEAR_CONFIG:
        return OutlierConfig(), None
    cfg = load_config(path)
    return cfg, Path(path).read_text()


def save_config(store: ResultsStore, text: str | None | bool) -> None:
    """Store what :func:`resolve_config` returned (under the run's lock)."""
    if text is not False:
        store.write_qa_config(text)  # type: ignore[arg-type]


def flagged_by_lot(store: ResultsStore) -> dict[str, set[str]]:
    return _flagged_units(store.read("units", columns=["lot", "unit", "flagged"]))


def _flagged_units(units: pd.DataFrame) -> dict[str, set[str]]:
    """Lot -> its flagged units (every lot of the units table, possibly with none)."""
    out: dict[str, set[str]] = {}
    if len(units) and "flagged" in units:
        for r in units[["lot", "unit", "flagged"]].itertuples():
            out.setdefault(str(r.lot), set())
            if r.flagged is not None and not pd.isna(r.flagged) and bool(r.flagged):
                out[str(r.lot)].add(str(r.unit))
    return out


def reflag_after_update(
    store: ResultsStore, touched: list[str], config: OutlierConfig
) -> tuple[list[LotFlags], list[str]]:
    """Leave every lot's flags as a re-flag of every lot would (the robust scale is pooled
    over all lots, so one lot's new values can move every lot's scores); return the flags of
    the touched lots and the lots whose reports must be rebuilt: the touched ones and any
    whose flagged units changed. Only the lots that can have changed are re-flagged
    (:func:`_reflag_fleet`)."""
    if not touched:
        return [], []
    all_lots = sorted(set(store.table_lots("summary")) | set(touched))
    lf, before, after = _reflag_fleet(store, touched, config)
    changed = {lot for lot in all_lots if before.get(lot, set()) != after.get(lot, set())}
    return [x for x in lf if x.lot in set(touched)], sorted(set(touched) | changed)


def reflag_lots(store: ResultsStore, lots: set[str] | list[str], config: OutlierConfig) -> list[LotFlags]:
    """Recompute the flags of the given lots from the whole summary (the robust scale is
    pooled over all lots: the summary is small, ~100 rows per unit, and read whole) and write
    them to the summary and units tables, rewriting only the lots whose rows changed."""
    return _reflag(store, lots, config)[0]


# the summary columns calib_core.outliers.apply_flags sets; it leaves every other one alone
_FLAG_COLUMNS = ("flagged", "flag_reason", "score", "lot_median")


def _lots_with_new_flags(before: pd.DataFrame, after: pd.DataFrame) -> list[str] | None:
    """Lots whose summary rows differ between ``before`` and ``after = apply_flags(before)``
    (same rows, same order): only the flag columns can differ, compared exactly (NaN equal
    to NaN, a missing value unequal to any value), as the store's skip-unchanged comparison
    would decide, without its per-lot frame comparison (~0.2 s when a lot differs)."""
    differs = np.zeros(len(after), dtype=bool)
    for col in _FLAG_COLUMNS:
        if col not in before:
            differs[:] = True
            break
        a, b = before[col], after[col]
        a_na, b_na = a.isna().to_numpy(), b.isna().to_numpy()
        both = ~a_na & ~b_na
        if col in ("score", "lot_median"):
            a_v, b_v = a.to_numpy(float, na_value=np.nan), b.to_numpy(float, na_value=np.nan)
            differs |= (a_na != b_na) | (both & (a_v != b_v))
        else:
            a_v, b_v = a.to_numpy(object), b.to_numpy(object)
            ne = np.zeros(len(a_v), dtype=bool)
            ne[both] = a_v[both] != b_v[both]
            differs |= (a_na != b_na) | ne
    lots = after["lot"].to_numpy(object, na_value=None)[differs]
    if any(x is None for x in lots):
        return None  # rows without a lot: let the store compare them (never seen)
    return sorted({str(x) for x in lots})


def _reflag(
    store: ResultsStore, lots: set[str] | list[str], config: OutlierConfig, keep_state: bool = False
) -> tuple[list[LotFlags], dict[str, set[str]], dict[str, set[str]]]:
    """reflag_lots, plus each lot's flagged units before and after (from the units table it
    reads and writes anyway). ``keep_state``: ``lots`` are all the lots, and the flag state
    (:func:`_reflag_fleet`) is written for the next run."""
    summary = store.read("summary")
    if not len(summary) or not lots:
        return [], {}, {}
    present = set(summary["lot"].dropna().astype(str))
    todo = sorted(set(map(str, lots)) & present)
    if not todo:
        return [], {}, {}
    lf = _flag(store, summary, config, todo)
    before, after = _write_flags(store, summary, lf, todo, lots=None, config=config)
    if keep_state:
        _write_flag_state(store, config, pooling_rows(summary, config), pooled_scales(summary, config))
    return lf, before, after


def unit_times(store: ResultsStore) -> dict[tuple[str, str], float]:
    """(lot, unit) -> acquisition time of its current calibration (POSIX s): the units
    table's ``acquired_at`` (its sessions' last ``session_start``), else when it was
    calibrated (``calibrated_at``: units whose sessions carry no ``session_start``)."""
    units = store.read("units")
    if not len(units):
        return {}
    when = pd.Series(pd.NaT, index=units.index, dtype="datetime64[ns, UTC]")
    for col in ("calibrated_at", "acquired_at"):  # acquired_at wins where present
        if col in units:
            t = pd.to_datetime(units[col], utc=True, errors="coerce", format="ISO8601")
            when = t.where(t.notna(), when)
    secs = (when - pd.Timestamp(0, tz="UTC")).dt.total_seconds()
    return {
        (str(lot), str(u)): float(t) for lot, u, t in zip(units["lot"], units["unit"], secs) if pd.notna(t)
    }


def _has_small_lots(store: ResultsStore, config: OutlierConfig) -> bool:
    """Whether any lot is judged against the fleet history (config.history_below)."""
    if not config.uses_history():
        return False
    units = store.read("units", columns=["lot", "unit"])
    if not len(units):
        return False
    return bool((units.groupby("lot", observed=True)["unit"].nunique() < config.history_below).any())


def _flag(
    store: ResultsStore, summary: pd.DataFrame, config: OutlierConfig, todo: list[str]
) -> list[LotFlags]:
    """flag_lots of ``todo``, with the thresholds simulated by earlier runs (kept in the
    store; new lot layouts are added to it) and the units' acquisition times (small lots'
    fleet history)."""
    cached = store.read_outlier_thresholds()
    remember_thresholds(cached)
    times = unit_times(store) if config.uses_history() else None
    lf = flag_lots(summary.astype({"lot": object, "unit": object}), config, todo, times)
    now = known_thresholds()
    if now != cached:  # new lot layouts simulated: keep them for the next process
        store.write_outlier_thresholds(now)
    return lf


def _write_flags(
    store: ResultsStore,
    summary: pd.DataFrame,
    lf: list[LotFlags],
    todo: list[str],
    lots: list[str] | None,
    config: OutlierConfig,
) -> tuple[dict[str, set[str]], dict[str, set[str]]]:
    """Write the flags ``lf`` of the lots ``todo`` to the summary and units tables:
    ``summary`` holds the stored rows of ``lots`` (None: every lot), and the units rows of
    those lots are read, the flags of those not in ``todo`` normalised (missing: not
    flagged). Only lots whose rows changed are rewritten. Returns each lot's flagged units
    before and after."""
    flagged_summary = apply_flags(summary, lf)
    # rows of lots whose flags changed are rewritten, the other lots' files left alone
    changed = _lots_with_new_flags(summary, flagged_summary)
    if changed is None:
        store.write("summary", flagged_summary, lots=lots, skip_unchanged=True, previous=summary)
    elif changed:
        in_changed = flagged_summary["lot"].astype(object).isin(changed).to_numpy()
        store.write("summary", flagged_summary[in_changed], lots=changed)
    units = store.read("units", lots=lots)
    units_before = units.copy()
    if len(units):
        flagged = {}
        for f in lf:
            for fl in f.flags:
                flagged.setdefault((fl.lot, fl.unit), []).append(f"[{fl.kind}] {fl.reason}")
        in_lots = units["lot"].astype(str).isin(todo).to_numpy()
        keys = list(zip(units["lot"].astype(str), units["unit"].astype(str)))
        units["flagged"] = [
            bool(flagged.get(k)) if m else bool(v) if pd.notna(v) else False
            for k, m, v in zip(keys, in_lots, units.get("flagged", [False] * len(units)))
        ]
        units["flag_reason"] = [
            "; ".join(flagged.get(k, [])) if m else (v if isinstance(v, str) else "")
            for k, m, v in zip(keys, in_lots, units.get("flag_reason", [""] * len(units)))
        ]
        store.write("units", units, lots=lots, skip_unchanged=True, previous=units_before)
        stamp_qa(store, units_before, units, lf, config)
    return _flagged_units(units_before), _flagged_units(units)


def qa_status(lot_flags: LotFlags, unit: str, config: OutlierConfig, when: str) -> dict:
    """The QA block of a unit's calibration file: ``pass``, ``flagged`` (every reason) or
    ``limits`` (a limit failed: the failed limits, and every other reason too), and the lot
    context it was judged in."""
    mine = [f for f in lot_flags.flags if f.unit == unit]
    failed = [f"{f.reason}" for f in mine if f.kind == KIND_LIMIT]
    status = "limits" if failed else "flagged" if mine else "pass"
    return {
        "status": status,
        "reasons": [f"[{f.kind}] {f.reason}" for f in mine],
        "failed_limits": failed,
        "lot": lot_flags.lot,
        "lot_units": lot_flags.n_units,
        "reference": lot_flags.reference,
        "reference_detail": lot_flags.reference_detail,
        "z_threshold": lot_flags.z_threshold_used,
        "note": lot_flags.note,
        "config": {
            "z_threshold": config.z_threshold,
            "family_alpha": config.family_alpha,
            "spread_factor": config.spread_factor,
            "min_units": config.min_units,
            "scale_pool": config.scale_pool,
            "history_units": config.history_units,
            "history_below": config.history_below,
            "history_location": config.history_location,
            "limits": [f"{lim.model}.{lim.parameter}: {lim.written or ''}" for lim in config.limits],
        },
        "judged_at": when,
    }


def stamp_qa(
    store: ResultsStore,
    before: pd.DataFrame,
    after: pd.DataFrame,
    lot_flags: list[LotFlags],
    config: OutlierConfig,
) -> list[str]:
    """Write the QA status into the current calibration file of every unit of the lots
    re-flagged (``lot_flags``) whose status is new: freshly calibrated (no flags yet), or
    whose flags changed. Each file is rewritten atomically and keeps its earlier statuses
    (``qa_history``); the lot's context goes to ``qa/<lot>.json``. Returns the files
    rewritten."""
    from schemas.calibration_file import CalibrationFileError, set_qa_status

    when = iso(utc_now())
    by_lot = {x.lot: x for x in lot_flags}
    prev = (
        {(str(r.lot), str(r.unit)): (r.flagged, r.flag_reason) for r in before.itertuples()}
        if len(before)
        else {}
    )
    done = []
    for lf in lot_flags:
        store.write_qa_lot(
            lf.lot,
            {
                "lot": lf.lot,
                "n_units": lf.n_units,
                "reference": lf.reference,
                "reference_detail": lf.reference_detail,
                "z_threshold": lf.z_threshold_used,
                "note": lf.note,
                "judged_at": when,
            },
        )
    for r in after.itertuples():
        lot, unit = str(r.lot), str(r.unit)
        lf = by_lot.get(lot)
        path = getattr(r, "calibration_file", None)
        if lf is None or not isinstance(path, str) or not path:
            continue
        old_flagged, old_reason = prev.get((lot, unit), (None, None))
        if (
            old_flagged is not None
            and not pd.isna(old_flagged)
            and bool(old_flagged) == bool(r.flagged)
            and old_reason == r.flag_reason
        ):
            continue  # judged before, same status
        try:
            set_qa_status(store.root / path, qa_status(lf, unit, config, when))
            done.append(path)
        except (OSError, CalibrationFileError) as exc:  # the flags stand; the file says less
            print(f"QA status of {lot}/{unit} not written to {path}: {exc}", file=sys.stderr)
    return done


# --- the flag state kept between runs --------------------------------------------------------------
# A lot's flags and scores depend on its own summary rows, the configuration, the flagging code
# and, through the pooled robust scales, on the other lots' means (calib_core.outliers.
# pooled_scales). cache/flag_state.parquet keeps, as the last re-flag left them: the pooled rows
# of every lot (pooling_rows: ~24 per unit), the pooled scales, the configuration and code they
# were computed with, and the (size, mtime, inode) of each lot's summary and units file. A lot
# whose files are unchanged since then still holds exactly the flags a re-flag would give it,
# as long as the pooled scales are the same: a re-flag after an update then re-flags only the
# touched lots and those whose files changed (reading only their files), and every lot when the
# pooled scales moved (any change of a scale changes every lot's scores). Exact, no tolerance:
# the stored scores are those of a re-flag of every lot.
FLAG_STATE_VERSION = 1


def _flag_state_key(config: OutlierConfig) -> str:
    """The configuration and flagging code the state was computed with (the source of
    calib_core.outliers: a new version of the rules makes the state stale)."""
    import dataclasses
    import hashlib

    import calib_core.outliers as outliers

    code = hashlib.sha256(Path(outliers.__file__).read_bytes()).hexdigest()[:16]
    return json.dumps(
        {"config": dataclasses.asdict(config), "outliers_source": code}, sort_keys=True, default=str
    )


def _pooled_doc(pooled: dict[tuple[str, str], tuple[float, tuple[int, ...]]]) -> list:
    """The pooled scales as JSON values (floats round-trip exactly through JSON)."""
    return [[m, p, scale, list(sizes)] for (m, p), (scale, sizes) in sorted(pooled.items())]


def _lot_files(store: ResultsStore) -> dict[str, dict[str, list[int] | None]] | None:
    """(size, mtime_ns, inode) of each lot's summary and units files; None when a table is
    a format-1.0 flat file or has rows without a lot (the state is then not used)."""
    stats = {name: store.partition_stats(name) for name in ("summary", "units")}
    if any(st is None or None in st for st in stats.values()):
        return None
    lots = set(stats["summary"]) | set(stats["units"])
    return {
        lot: {name: (list(st[lot]) if lot in st else None) for name, st in stats.items()}
        for lot in sorted(lots)
    }


def _write_flag_state(store: ResultsStore, config: OutlierConfig, rows: pd.DataFrame, pooled: dict) -> None:
    """Record the state after a re-flag that left every lot as a re-flag of all would."""
    files = _lot_files(store)
    if files is None:
        return
    rows = rows.astype({"lot": str, "unit": str, "model": str, "parameter": str})
    store.write_flag_state(
        rows.sort_values("lot", kind="stable").reset_index(drop=True),
        {
            "version": FLAG_STATE_VERSION,
            "key": _flag_state_key(config),
            "pooled": _pooled_doc(pooled),
            "files": files,
        },
    )


def _reflag_fleet(
    store: ResultsStore, touched: list[str], config: OutlierConfig
) -> tuple[list[LotFlags], dict[str, set[str]], dict[str, set[str]]]:
    """:func:`_reflag` of every lot, re-flagging only the touched lots and those whose files
    changed since the flag state was written, while the pooled scales are unchanged; every
    lot (and a new state) when there is no usable state or the scales moved. Returns the
    flags of the lots re-flagged (the touched ones among them) and the flagged units before
    and after of the lots whose units rows were read."""
    state = store.read_flag_state()
    files = _lot_files(store)
    # a small lot is judged against the history of earlier lots, which the pooled scales
    # do not summarise: every lot is re-flagged then
    if state is not None and files is not None and not _has_small_lots(store, config):
        rows, doc = state
        if doc.get("version") == FLAG_STATE_VERSION and doc.get("key") == _flag_state_key(config):
            done = _reflag_changed_lots(store, touched, config, rows, doc, files)
            if done is not None:
                return done
    all_lots = sorted(set(store.table_lots("summary")) | set(map(str, touched)))
    return _reflag(store, all_lots, config, keep_state=True)


def _reflag_changed_lots(
    store: ResultsStore, touched: list[str], config: OutlierConfig, rows: pd.DataFrame, doc: dict, files: dict
) -> tuple[list[LotFlags], dict[str, set[str]], dict[str, set[str]]] | None:
    """The partial re-flag of :func:`_reflag_fleet`; None when the pooled scales moved."""
    known = doc.get("files") or {}
    dirty = sorted({lot for lot, f in files.items() if known.get(lot) != f} | set(map(str, touched)))
    clean = set(files) - set(dirty)
    if not clean:  # every lot changed (a nightly run of the whole fleet): the full re-flag
        return None
    summary = store.read("summary", lots=dirty)
    kept = rows[rows["lot"].isin(clean).to_numpy()]
    pool = pd.concat(
        [pooling_rows(summary, config).astype({"lot": str, "unit": str}), kept], ignore_index=True
    )
    pooled = pooled_scales(pool, config)
    if _pooled_doc(pooled) != doc.get("pooled"):
        return None
    present = set(summary["lot"].dropna().astype(str))
    todo = sorted(set(dirty) & present)
    lf = []
    if todo:
        # the clean lots' pooled rows stand in for their summary: flag_lots takes the pooled
        # scales from them and flags only the lots in todo
        lf = _flag(
            store,
            pd.concat([summary, kept.assign(std=np.nan, n_reps=np.nan)], ignore_index=True),
            config,
            todo,
        )
    before, after = _write_flags(store, summary, lf, todo, lots=dirty, config=config)
    _write_flag_state(store, config, pool, pooled)
    return lf, before, after


def unit_navigation(ur: UnitResult) -> pd.DataFrame | None:
    """Navigation drift of the unit's first repetition with a fully determined lever arm."""
    from calib_core.navigation import navigation_table

    if not ur.calibrated:
        return None
    for rep in ur.outcome.calibration.reps:
        static, lever = rep.fits.get("accel_static"), rep.fits.get("lever_arm")
        if static is not None and lever is not None and not lever.undetermined:
            return navigation_table(static, lever)
    return None


def write_reports(
    results: str | Path, lots: list[str], units: tuple[str, ...] = ()
) -> tuple[list[str], list[str]]:
    """Lot reports, unit reports of ``units`` (reruns) and the fleet index; returns (paths
    written, problems). A report failure never undoes a calibration.

    The reports share one read view of the store, so a unit report and its lot's report read
    the lot's tables once; each lot's cached rows are dropped once its report is written
    (memory: one lot)."""
    written, problems = [], []
    try:
        from reports.store import StoreView

        view = StoreView(results)
    except ImportError as exc:
        return [], [f"reports not available ({exc}); no report written"]
    for unit in units:
        try:
            from reports.unit import write_unit_report

            written.append(str(write_unit_report(results, unit, view=view)))
        except Exception as exc:
            problems.append(f"unit report {unit}: {type(exc).__name__}: {exc}")
    try:
        from reports.lot import write_lot_report
    except ImportError as exc:
        return written, problems + [f"reports.lot not available ({exc}); no lot report written"]
    for lot in sorted(lots):
        try:
            written.append(str(write_lot_report(results, lot, view=view)))
        except Exception as exc:
            problems.append(f"lot report {lot}: {type(exc).__name__}: {exc}")
        finally:
            view.forget_lot(lot)
        if len(lots) > 1:  # each lot report's ~100 MB of pages back before the next one
            release_memory()  # (flows.memory); a rerun's single lot does not pay the 0.1 s
    try:
        from reports.index import write_fleet_index

        written.append(str(write_fleet_index(results, view=view)))
    except ImportError as exc:
        problems.append(f"reports.index not available ({exc}); no fleet index written")
    except Exception as exc:
        problems.append(f"fleet index: {type(exc).__name__}: {exc}")
    return written, problems


def reports_to_rebuild(store: ResultsStore) -> list[str]:
    """Lots whose report is missing or older than the lot's summary or units file (a run
    that died, or found the disk full, while writing it); every lot when the fleet index is
    missing (it is written with any lot's report)."""
    lots = sorted(set(store.table_lots("units")) | set(store.table_lots("summary")))
    if not lots:
        return []
    if not (store.reports_dir / "index.html").is_file():
        return lots
    out = []
    for lot in lots:
        try:
            made = (store.reports_dir / f"{lot}.html").stat().st_mtime_ns
        except OSError:
            out.append(lot)
            continue
        newest = max(
            (
                p.stat().st_mtime_ns
                for name in ("units", "summary")
                for lt, p in store.partitions(name).items()
                if lt == lot and p.exists()
            ),
            default=0,
        )
        if newest > made:
            out.append(lot)
    return out


def known_names(dataset: str | Path, field: str) -> str:
    """``units there: U0001, U0002, ...`` (or lots) of a dataset, for a message."""
    root = Path(dataset)
    names = set()
    try:
        for lot_dir in root.iterdir():
            if not lot_dir.name.startswith("lot="):
                continue
            if field == "lot":
                names.add(lot_dir.name[4:])
                continue
            for unit_dir in lot_dir.iterdir():
                if unit_dir.name.startswith("unit="):
                    names.add(unit_dir.name[5:])
    except OSError:
        pass
    shown = sorted(names)
    more = f", ... ({len(shown)} in all)" if len(shown) > 20 else ""
    return f"{field}s there: {', '.join(shown[:20]) or 'none'}{more}"


def make_batches(jobs: list[UnitJob], batch_size: int) -> list[list[UnitJob]]:
    batch_size = max(1, int(batch_size))
    return [jobs[i : i + batch_size] for i in range(0, len(jobs), batch_size)]


def new_run_id() -> str:
    return utc_now().strftime("%Y%m%dT%H%M%SZ") + "-" + uuid.uuid4().hex[:6]


# --- Prefect tasks and flows ------------------------------------------------------------------
@task(name="calibrate-units", persist_result=False, cache_policy=NO_CACHE, log_prints=False)
def calibrate_units_task(jobs: list[UnitJob], run_discovery: bool = True) -> list[UnitResult]:
    """One batch of units: paths in, fitted results out (in memory only). The work runs in
    the flow's worker processes when the run opened them (runner ``processes``/``auto``), on
    the Dask cluster when the ``dask`` runner opened it, else here."""
    return run_in_pool(calibrate_batch, jobs, run_discovery)


class _Progress:
    """One terminal line per lot each time a batch brings units of it: "lot L1: 8/16 units
    (0 failed sessions), 3.2 s". A closed terminal pipe never fails the run."""

    def __init__(self, total: int, stream=None, per_lot: dict[str, int] | None = None):
        self.total = total
        self.done = 0
        self.failed_sessions = 0
        self.per_lot = dict(per_lot or {})
        self.lot_done: Counter = Counter()
        self.lot_failed: Counter = Counter()
        self.stream = stream if stream is not None else sys.stderr
        self.t0 = time.monotonic()

    def update(self, results: list[UnitResult]) -> str:
        self.done += len(results)
        self.failed_sessions += sum(r.n_failed for r in results)
        for r in results:
            self.lot_done[r.lot] += 1
            self.lot_failed[r.lot] += r.n_failed
        elapsed = time.monotonic() - self.t0
        lines = [
            f"lot {lot}: {self.lot_done[lot]}/{self.per_lot.get(lot, '?')} units"
            + (f" ({self.lot_failed[lot]} failed sessions)" if self.lot_failed[lot] else "")
            + f", {elapsed:.1f} s"
            for lot in sorted({r.lot for r in results})
        ]
        if self.stream:
            try:
                for line in lines:
                    print(line, file=self.stream, flush=True)
            except (BrokenPipeError, ValueError):  # the terminal's pipe closed: keep working
                self.stream = False
        return f"units {self.done}/{self.total} done, failed sessions {self.failed_sessions}, {elapsed:.1f} s"


DEFAULT_MAX_IN_FLIGHT = 4  # batches submitted at once: 2 workers busy + 2 queued
DASK_MAX_IN_FLIGHT = DASK_TASK_THREADS  # as many as the dask runner's task threads


def _run_batches(
    jobs: list[UnitJob],
    batch_size: int,
    run_discovery: bool,
    on_progress: Callable[[list[UnitResult]], None],
    on_lot: Callable[[str, list[UnitResult]], None],
    max_in_flight: int = DEFAULT_MAX_IN_FLIGHT,
) -> None:
    """Calibrate the jobs (sorted by lot) in batches; hand each lot's results (sorted by
    unit) to ``on_lot`` as soon as every unit of the lot is done, then forget them.

    Memory is bounded by one lot plus the batches in flight: at most ``max_in_flight``
    batches are submitted at a time (Prefect's ``as_completed`` keeps every future it is
    given, and each future its result, until the iteration ends, so the futures of a whole
    fleet submitted at once would hold every unit's results), and a future is dropped once
    its result is taken."""
    pending = deque(make_batches(jobs, batch_size))
    units_left = Counter(j.lot for j in jobs)
    done: dict[str, list[UnitResult]] = {}
    window: list = []
    max_in_flight = max(1, int(max_in_flight))
    while pending or window:
        while pending and len(window) < max_in_flight:
            window.append(calibrate_units_task.submit(pending.popleft(), run_discovery))
        fut = next(as_completed(window))
        window = [f for f in window if f is not fut]
        batch = fut.result()
        del fut
        on_progress(batch)
        for r in batch:
            done.setdefault(r.lot, []).append(r)
            units_left[r.lot] -= 1
        del batch
        for lot in sorted(lot for lot in done if units_left[lot] == 0):
            on_lot(lot, sorted(done.pop(lot), key=lambda r: r.unit))


@flow(
    name="nightly-fleet-calibration",
    persist_result=False,
    log_prints=False,
    task_runner=default_task_runner(),
)
def nightly_flow(
    dataset: str,
    results: str,
    force: bool = False,
    batch_size: int = DEFAULT_BATCH_SIZE,
    config: str | None = None,
    wait: bool = False,
    run_discovery: bool = True,
    progress: bool = True,
    max_in_flight: int = DEFAULT_MAX_IN_FLIGHT,
    runner: str | None = None,
    unit_reports: bool = False,
    follow_symlinks: bool = False,
) -> dict:
    """Find sessions, calibrate new/changed units in batches, store lot by lot, flag,
    report. ``runner`` (flows.task_runners kinds) decides whether the batches' work goes to
    worker processes; ``dask`` means the task runner already sends it elsewhere."""
    logger = get_run_logger()
    run_id = new_run_id()
    store = ResultsStore(Path(results))
    cfg, cfg_text = resolve_config(store, config)
    version = runtime.code_version()
    with store.lock(owner=run_id, wait=wait):
        store.check()  # a damaged store is refused before anything is written
        save_config(store, cfg_text)
        t0 = time.monotonic()
        log: dict[str, Any] = {
            "run_id": run_id,
            "kind": "nightly",
            "start": iso(utc_now()),
            "dataset": str(dataset),
            "results": str(results),
            "force": force,
            "code_version": version,
            "config": config,
            "batch_size": batch_size,
        }
        if runner != "dask":
            # a served run has no launcher that started the workers' forkserver while Prefect
            # started (nightly_fleet_calibration): start it now, so that its imports overlap
            # this process's own (the numerics, on first use); a no-op when it runs already
            prestart_unit_work_pool(runner, dataset)
        # runs that died before their end (SIGKILL, power loss): what they stored is complete
        # (atomic writes, fingerprints last), but their flags and reports may not be
        interrupted = interrupted_runs(store)
        if interrupted:
            log["recovering_runs"] = interrupted
        preloaded = _await_preload()
        if preloaded is not None:
            log["preload"] = preloaded
        refs, path_errors = find_sessions(dataset, follow_symlinks=follow_symlinks)
        digests = DigestCache(store.read_digest_cache())
        jobs, skipped = plan_units(refs, store.fingerprints(), force, digests)
        # --- hook: units calibrated from field recordings (lot=L/unit=U/field/, flows.field_units)
        from flows.field_units import add_field_units

        jobs, skipped, path_errors = add_field_units(dataset, store, force, refs, jobs, skipped, path_errors)
        # --- end of hook
        current = {os.path.join(str(r.path), n) for r in refs for n in ("steps.parquet", "samples.parquet")}
        if digests.read or set(digests.entries) - current:  # files of moved datasets go
            store.write_digest_cache({p: e for p, e in digests.entries.items() if p in current})
        if run_discovery and not _discovery_available():
            logger.warning("model discovery skipped: calib_core.discovery is not available")
        log.update(
            {
                "sessions_found": len(refs),
                "units_found": len(jobs) + len(skipped),
                "units_to_calibrate": len(jobs),
                "units_skipped": len(skipped),
                "path_errors": [e.to_dict() for e in path_errors],
                "progress": {"units_done": 0, "units_total": len(jobs)},
            }
        )
        store.write_run(run_id, log)
        prog = _Progress(
            len(jobs), stream=sys.stderr if progress else False, per_lot=Counter(j.lot for j in jobs)
        )

        def on_progress(batch: list[UnitResult]) -> None:
            line = prog.update(batch)
            log["progress"] = {
                "units_done": prog.done,
                "units_total": prog.total,
                "failed_sessions": prog.failed_sessions,
                "line": line,
            }
            store.write_run(run_id, log)

        tally = RunTally()
        store_s = [0.0]
        writes: deque = deque()

        def store_lot(lot_results: list[UnitResult]) -> None:
            t = time.monotonic()
            tally.add(lot_results, store_results(store, lot_results, run_id, version))
            del lot_results[:]  # this thread's reference: the lot's results can go now
            release_memory()  # its frames' pages back before the next lot (flows.memory)
            store_s[0] += time.monotonic() - t

        def on_lot(lot: str, lot_results: list[UnitResult]) -> None:
            # stored as soon as the lot is complete, then dropped: memory is one lot, not the
            # fleet; flags and reports wait for every lot (the robust scale is pooled). The
            # writing runs in one writer thread so that batches keep being submitted meanwhile
            # (with worker processes the workers would otherwise wait for it); at most one
            # more lot waits behind the one being written (memory: two lots), and a failed
            # write fails the run as before
            while len(writes) >= 2:
                writes.popleft().result()
            writes.append(writer.submit(store_lot, lot_results))

        if jobs:
            pooled = runner != "dask" and uses_unit_work_pool(runner, len(jobs))
            log["unit_work"] = "worker processes" if pooled else "task runner"
            with (
                ThreadPoolExecutor(1, thread_name_prefix="mimucal-store") as writer,
                unit_work_pool(None if runner == "dask" else runner, len(jobs) if pooled else 0),
            ):
                _run_batches(jobs, batch_size, run_discovery, on_progress, on_lot, max_in_flight)
                t_cal = time.monotonic() - t0
                while writes:
                    writes.popleft().result()
        else:
            t_cal = time.monotonic() - t0
        # calibration_s: the fit phase (read ... aggregate) until the last batch is back; the
        # storing of lots overlaps it (store_s: time spent storing, in the writer thread)
        lots = sorted(tally.lots | (set(store.lots()) if interrupted else set()))
        # the pages the fit phase and the lots' storing freed (in the task runner's and the
        # writer's malloc arenas), given back before flags and reports allocate theirs in
        # this thread's arena (flows.memory; docs/benchmarks.md)
        release_memory()
        lot_flags, report_lots = reflag_after_update(store, lots, cfg)
        # reports that are missing or older than their lot's tables (a run that died or hit
        # a full disk while writing them) are rebuilt too
        report_lots = sorted(set(report_lots) | set(reports_to_rebuild(store)))
        release_memory()
        # unit reports (``unit_reports``): every unit of the lots whose report is rewritten
        units = (
            tuple(sorted({str(u) for u in store.read("units", lots=report_lots, columns=["unit"])["unit"]}))
            if unit_reports and report_lots
            else ()
        )
        reports, problems = write_reports(results, report_lots, units) if report_lots else ([], [])
        for p in problems:
            logger.warning(p)
        flagged = sorted({f"{f.lot}/{f.unit}" for lf in lot_flags for f in lf.flags})
        log.update(
            {
                "end": iso(utc_now()),
                "elapsed_s": round(time.monotonic() - t0, 3),
                "calibration_s": round(t_cal, 3),
                "store_s": round(store_s[0], 3),
                **tally.log_fields(),
                "flagged_units": flagged,
                "flags": [lf.to_dict() for lf in lot_flags],
                "lots_touched": lots,
                "reports": reports,
                "report_problems": problems,
                "discovery_notes": sorted(tally.discovery_notes),
                "summary": None,
            }
        )
        log["summary"] = summary_line(log)
        store.write_run(run_id, log)
        for rid in interrupted:  # recovered: later runs need not redo it
            doc = store.read_run(rid)
            doc.update({"interrupted": True, "recovered_by": run_id})
            store.write_run(rid, doc)
    return jsonable(log)


def interrupted_runs(store: ResultsStore) -> list[str]:
    """Ids of nightly runs whose log has a start but no end and that no later run recovered.
    Called while holding the lock, so none of them is still running."""
    out = []
    for p in store.runs():
        try:
            doc = json.loads(p.read_text())
        except (OSError, ValueError):
            continue
        if doc.get("kind") == "nightly" and "end" not in doc and "recovered_by" not in doc:
            out.append(str(doc.get("run_id", p.stem)))
    return out


def summary_line(log: dict, wall_s: float | None = None) -> str:
    """One line: units, sessions, flags; the flow's time, or ``wall_s`` (the command's wall
    time) with the flow's time in brackets."""
    return (
        f"{log.get('kind', 'run')} {log['run_id']}: {log.get('units_found', '?')} units "
        f"({log.get('units_calibrated', 0)} calibrated, {log.get('units_skipped', 0)} "
        f"unchanged, {len(log.get('units_failed', []))} failed, {len(log.get('units_stale', {}))}"
        f" stale), {log.get('sessions_calibrated', 0)} sessions ok, "
        f"{len(log.get('failed_sessions', []))} failed, {len(log.get('path_errors', []))} bad "
        f"paths, flagged units: {', '.join(log.get('flagged_units', [])) or 'none'}; "
        + (
            f"{log.get('elapsed_s', 0):.1f} s"
            if wall_s is None
            else f"{wall_s:.1f} s wall ({log.get('elapsed_s', 0):.1f} s in the flow)"
        )
    )


@flow(name="lot-quality-report", persist_result=False, log_prints=False)
def lot_report_flow(results: str, lot: str, config: str | None = None, wait: bool = False) -> dict:
    store = ResultsStore(Path(results))
    cfg, cfg_text = resolve_config(store, config)
    with store.lock(owner=f"report-{lot}", wait=wait):
        store.check()
        if lot not in store.table_lots("summary") and lot not in store.table_lots("sessions"):
            lots = sorted(set(store.table_lots("summary")) | set(store.table_lots("sessions")))
            raise LookupError(
                f"lot {lot!r} is not in the results store {results} (lots there: {', '.join(lots) or 'none'})"
            )
        save_config(store, cfg_text)
        # the lot as touched: with a new configuration every lot is re-flagged (the flag
        # state is of another configuration) and the reports of lots whose flags changed
        # are rebuilt too
        lf, report_lots = reflag_after_update(store, [lot], cfg)
        reports, problems = write_reports(results, report_lots)
    return {"lot": lot, "reports": reports, "problems": problems, "flags": [f.to_dict() for f in lf]}


# Modules a flow needs once it runs (the numerics' first import pulls in scipy.stats and
# scipy.linalg, ~1.5-2 s CPU; the report builders plotly). rerun_unit and
# nightly_fleet_calibration import them in a thread while Prefect starts (which mostly waits
# for its API server, a subprocess), so that the flow does not pay them; the flow waits for
# that thread first and logs what it cost (run log: ``preload``).
FLOW_PRELOAD = (
    "calib_core.discovery",
    "calib_core.zhang2017",
    "calib_core.navigation",
    "calib_core.pipeline",
    "schemas.unit_document",
    "reports.unit",
    "reports.lot",
    "reports.index",
)


class _Preload:
    """Import modules in a daemon thread; ``wait()`` joins it and says what it cost. A module
    that fails to import here is simply imported (and fails) where it is used."""

    def __init__(self, modules: tuple[str, ...]) -> None:
        import threading

        self.modules = modules
        self.wall_s = self.cpu_s = 0.0
        self.failed: list[str] = []
        self._thread = threading.Thread(target=self._run, name="mimucal-preload", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        import importlib

        t, c = time.perf_counter(), time.thread_time()
        for m in self.modules:
            try:
                importlib.import_module(m)
            except Exception as exc:  # noqa: BLE001 (reported, and raised again where used)
                self.failed.append(f"{m}: {type(exc).__name__}: {exc}")
        self.wall_s, self.cpu_s = time.perf_counter() - t, time.thread_time() - c

    def wait(self) -> dict[str, Any]:
        t = time.perf_counter()
        self._thread.join()
        return {
            "modules": len(self.modules),
            "import_wall_s": round(self.wall_s, 3),
            "import_cpu_s": round(self.cpu_s, 3),
            "waited_in_flow_s": round(time.perf_counter() - t, 3),
            **({"failed": self.failed} if self.failed else {}),
        }


_pending_preload: _Preload | None = None


@contextmanager
def _preloading():
    """Around a flow call: import FLOW_PRELOAD in a thread meanwhile (Prefect's start-up)."""
    global _pending_preload
    preload = _pending_preload = _Preload(FLOW_PRELOAD)
    try:
        yield
    finally:
        _pending_preload = None
        preload.wait()  # a flow that never started leaves no import running behind it


def _await_preload() -> dict[str, Any] | None:
    """In a flow: wait for the launcher's preload (if any) and say what it cost."""
    global _pending_preload
    preload, _pending_preload = _pending_preload, None
    return preload.wait() if preload is not None else None


@flow(name="rerun-unit", persist_result=False, log_prints=False)
def rerun_flow(
    dataset: str,
    results: str,
    unit: str,
    config: str | None = None,
    wait: bool = False,
    run_discovery: bool = True,
    follow_symlinks: bool = False,
) -> dict:
    """Recalibrate one unit now; its rows are replaced only if it succeeds (otherwise its last
    good calibration stays and is marked stale); its lot is re-flagged and its report rebuilt.

    The unit is calibrated in the flow's own thread, not in a Prefect task: a rerun is one
    unit, and the first task run of a process costs more Prefect bookkeeping than the batching
    of tasks saves (the flow run, its state and the run log record the rerun)."""
    run_id = new_run_id()
    store = ResultsStore(Path(results))
    cfg, cfg_text = resolve_config(store, config)
    version = runtime.code_version()
    with store.lock(owner=run_id, wait=wait):
        store.check()
        save_config(store, cfg_text)
        t0 = time.monotonic()
        phases: dict[str, float] = {}
        cpu: dict[str, float] = {}
        t, c = time.monotonic(), time.process_time()

        def phase(name: str) -> None:
            nonlocal t, c
            phases[name], cpu[name] = time.monotonic() - t, time.process_time() - c
            t, c = time.monotonic(), time.process_time()

        preloaded = _await_preload()
        refs, path_errors = find_sessions(dataset, unit=unit, follow_symlinks=follow_symlinks)
        # --- hook: a unit calibrated from field recordings (flows.field_units)
        from flows.field_units import field_unit_job

        field_job = None if refs else field_unit_job(dataset, unit)
        # --- end of hook
        if not refs and field_job is None:
            why = "; ".join(str(e) for e in path_errors) or "no session directory found"
            raise LookupError(
                f"unit {unit!r}: no session under {dataset} ({why}); {known_names(dataset, 'unit')}"
            )
        lot = refs[0].key.lot if refs else field_job.lot
        job = field_job or UnitJob(lot, unit, refs, "rerun")
        log: dict[str, Any] = {
            "run_id": run_id,
            "kind": "rerun",
            "start": iso(utc_now()),
            "dataset": str(dataset),
            "results": str(results),
            "unit": unit,
            "lot": lot,
            "code_version": version,
            "units_found": 1,
            "units_skipped": 0,
            "path_errors": [e.to_dict() for e in path_errors],
        }
        if preloaded is not None:
            log["preload"] = preloaded
        res = calibrate_batch([job], run_discovery)
        for r in res:
            try:
                r.navigation = unit_navigation(r)
            except Exception as exc:  # the drift figure must not cost the unit its calibration
                r.discovery_note = "; ".join(
                    filter(None, [r.discovery_note, f"navigation replay failed: {exc}"])
                )
        phase("calibrate")
        stored = store_results(store, res, run_id, version)  # reads/rewrites its lot only
        phase("store")
        lf, report_lots = reflag_after_update(store, [lot], cfg)
        report_lots = sorted(set(report_lots) | set(reports_to_rebuild(store)))
        phase("reflag")
        reports, problems = write_reports(results, report_lots, units=(unit,))
        phase("reports")
        failed = [
            {"session": str(s.key), "code": s.code, "message": s.message}
            for r in res
            for s in r.outcome.sessions
            if s.status == "failed"
        ]
        log.update(
            {
                "end": iso(utc_now()),
                "elapsed_s": round(time.monotonic() - t0, 3),
                "units_calibrated": len(stored["calibrated"]),
                "units_stale": stored["stale"],
                "units_failed": [f"{lot}/{unit}"] if not res[0].calibrated else [],
                "unit_errors": [
                    {"unit": f"{lot}/{unit}", "code": r.error_code, "message": r.error}
                    for r in res
                    if r.error_code
                ],
                "sessions_calibrated": sum(1 for s in res[0].outcome.sessions if s.status != "failed"),
                "failed_sessions": failed,
                "flagged_units": sorted({f"{f.lot}/{f.unit}" for x in lf for f in x.flags}),
                "flags": [x.to_dict() for x in lf],
                "reports": reports,
                "report_problems": problems,
                "phases_s": {k: round(v, 3) for k, v in phases.items()},
                # CPU seconds of the process per phase (wall time is unreliable on a shared machine)
                "phases_cpu_s": {k: round(v, 3) for k, v in cpu.items()},
            }
        )
        log["summary"] = summary_line(log)
        store.write_run(run_id, log)
    return jsonable(log)


# --- entry points --------------------------------------------------------------------------------
def nightly_fleet_calibration(
    dataset: str | Path,
    results: str | Path,
    force: bool = False,
    dask_address: str | None = None,
    batch_size: int = DEFAULT_BATCH_SIZE,
    config: str | Path | None = None,
    wait: bool = False,
    run_discovery: bool = True,
    progress: bool = True,
    runner: str | None = None,
    unit_reports: bool = False,
    follow_symlinks: bool = False,
) -> dict:
    """Run the nightly flow once: Dask at ``dask_address``, else the local ``runner``
    (``auto`` by default: worker processes from 24 units to calibrate, else a thread pool;
    see flows.task_runners)."""
    if not wait:  # a clear refusal, not a failed flow run in Prefect's database
        ResultsStore(Path(results)).ensure_unlocked()
    ResultsStore(Path(results)).check()  # and a damaged store, before Prefect starts
    kind = "dask" if dask_address else resolve_kind(runner)
    task_runner = make_task_runner(dask_address, kind=None if dask_address else kind)
    # Dask may have many workers: keep them all fed (memory: this many batches in flight)
    in_flight = DASK_MAX_IN_FLIGHT if kind == "dask" else DEFAULT_MAX_IN_FLIGHT
    if kind != "dask":  # worker processes' imports while Prefect starts, not in the fit phase
        prestart_unit_work_pool(kind, dataset)
    with _preloading(), runtime.run_settings():
        return nightly_flow.with_options(task_runner=task_runner)(
            str(dataset),
            str(results),
            force=force,
            batch_size=batch_size,
            config=None if config is None else str(config),
            wait=wait,
            run_discovery=run_discovery,
            progress=progress,
            max_in_flight=in_flight,
            runner=kind,
            unit_reports=unit_reports,
            follow_symlinks=follow_symlinks,
        )


def lot_quality_report(
    results: str | Path, lot: str, config: str | Path | None = None, wait: bool = False
) -> dict:
    if not wait:
        ResultsStore(Path(results)).ensure_unlocked()
    store = ResultsStore(Path(results))
    store.check()
    lots = set(store.table_lots("summary")) | set(store.table_lots("sessions"))
    if lot not in lots:  # before Prefect starts: one line, no failed flow run
        raise LookupError(
            f"lot {lot!r} is not in the results store {results} (lots there: "
            f"{', '.join(sorted(lots)) or 'none'})"
        )
    with runtime.run_settings():
        return lot_report_flow(str(results), lot, None if config is None else str(config), wait)


def rerun_unit(
    dataset: str | Path,
    results: str | Path,
    unit: str,
    config: str | Path | None = None,
    wait: bool = False,
    run_discovery: bool = True,
    follow_symlinks: bool = False,
) -> dict:
    if not wait:
        ResultsStore(Path(results)).ensure_unlocked()
    ResultsStore(Path(results)).check()
    refs, path_errors = find_sessions(dataset, unit=unit, follow_symlinks=follow_symlinks)
    from flows.field_units import field_unit_job  # hook: field units (flows.field_units)

    if not refs and field_unit_job(dataset, unit) is None:  # before Prefect: one line, no failed flow run
        why = "; ".join(str(e) for e in path_errors) or "no session directory found"
        raise LookupError(
            f"unit {unit!r}: no session under {dataset} ({why}); {known_names(dataset, 'unit')}"
        )
    with _preloading(), runtime.run_settings():
        return rerun_flow(
            str(dataset),
            str(results),
            unit,
            None if config is None else str(config),
            wait,
            run_discovery,
            follow_symlinks,
        )
