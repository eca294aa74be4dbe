"""Prefect flows: the nightly fleet calibration, the lot report rebuild and the single-unit
rerun. Orchestration only: the work is :mod:`flows.unit_pipeline` (per session/unit), the
store's rows :mod:`schemas.store_rows`, the flags :mod:`schemas.flagging` (its decisions
:mod:`calib_core.flag_decisions`, its rules :mod:`calib_core.outliers`), the run's
configuration :mod:`schemas.limits` and :mod:`reports`. A night: plan the units whose
sessions changed, calibrate them in batches and store each lot as it completes, re-flag the
lots touched, write their reports, log the run (:func:`nightly_flow`).

Granularity: one Prefect task per *batch of units* (at most ``batch_size``, default 8): a
task's own cost, small with the thread pool and larger with a process pool or Dask
(docs/flows.md), is shared by the batch's units. Tasks receive session paths, never arrays,
and return fitted results in memory (``persist_result=False``, no cache policy): Prefect
writes no sample data.

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

import pandas as pd  # noqa: E402
from prefect import flow, get_run_logger, task  # noqa: E402
from prefect.cache_policies import NO_CACHE  # noqa: E402
from prefect.futures import as_completed  # noqa: E402

from flows.compute_pool import discard_prestarted_workers, run_in_pool  # noqa: E402
from flows.field_units import field_unit_job  # noqa: E402
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
    failed_unit_result,
)
from schemas.dataset import DigestCache, SessionRef, find_sessions  # noqa: E402
from schemas.field_dataset import find_field_recordings  # noqa: E402
from schemas.flagging import reflag_after_update  # noqa: E402
from schemas.limits import resolve_config, save_config  # noqa: E402
from schemas.protocol_notes import notes_of  # noqa: E402
from schemas.results_store import (  # noqa: E402
    ResultsStore,
    iso,
    jsonable,
    utc_now,
)
from schemas.store_rows import StoreRows, remove_files, unit_store_rows, write_unit_tables  # noqa: E402
from schemas.unit_plan import (  # noqa: E402,F401  (plan_units, make_batches re-exported)
    make_batches,
    plan_unit_jobs,
    plan_units,
)

DEFAULT_BATCH_SIZE = 8


# --- plain-Python pieces (tested without Prefect) ------------------------------------------------
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
    rows = StoreRows()
    previous_units = store.read(
        "units",
        lots={ur.lot for ur in results},
        columns=["lot", "unit", "calibration_file", "calibrated_at", "acquired_at"],
    )
    prev_state = {(r.lot, r.unit): r for r in previous_units.itertuples()}
    for i, ur in enumerate(results):
        unit_rows = StoreRows()
        try:
            unit_store_rows(store, ur, unit_rows, prev_state, run_id, code_version, when, stamp)
        except Exception as exc:  # noqa: BLE001 - one unit never fails the flow
            if unit_rows.new_files:
                remove_files(unit_rows.new_files)
            failed = failed_unit_result(ur.lot, ur.unit, "storing its results", exc, ur.outcome)
            failed.diagnosis, failed.discovery_note = None, ur.discovery_note
            results[i] = ur = failed
            unit_rows = StoreRows()
            unit_store_rows(store, ur, unit_rows, prev_state, run_id, code_version, when, stamp)
        rows.extend(unit_rows)
    try:
        write_unit_tables(store, results, rows)
    except BaseException:
        if not rows.new_files_referenced:  # no table points to them: the run added nothing
            remove_files(rows.new_files)
        raise
    return {
        "calibrated": sorted(f"{lot}/{u}" for lot, u in rows.ok_units),
        "stale": {f"{lot}/{u}": w for (lot, u), w in rows.stale_units.items()},
    }


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
    # lot -> (unit, protocol notes) of each calibrated session that has some
    protocol_notes: dict[str, list[tuple[str, list[str]]]] = field(default_factory=dict)

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
        for r in results:
            for s in r.outcome.sessions:
                if s.status != "failed" and s.protocol_notes:
                    self.protocol_notes.setdefault(r.lot, []).append((r.unit, list(s.protocol_notes)))

    def log_fields(self) -> dict[str, Any]:
        # sorted as the run log had them when every unit was stored at once
        return {
            "units_calibrated": len(self.calibrated),
            "units_stale": {f"{lot}/{u}": self.stale[(lot, u)] for lot, u in sorted(self.stale)},
            "units_failed": sorted(self.failed_units),
            "unit_errors": sorted(self.unit_errors, key=lambda e: e["unit"]),
            "sessions_calibrated": self.sessions_calibrated,
            "failed_sessions": [f for _, f in sorted(self.failed_sessions, key=lambda x: x[0])],
            # what each lot's protocol cannot observe, once per lot (not a session warning)
            "protocol_notes": [
                {"lot": lot, "note": n.text, "sessions": n.sessions, "units": n.units}
                for lot in sorted(self.protocol_notes)
                for n in notes_of(self.protocol_notes[lot])
            ],
        }


def unit_navigation(ur: UnitResult) -> pd.DataFrame | None:
    """Navigation drift of a calibrated unit (calib_core.sim.navigation.unit_navigation_table)."""
    from calib_core.sim.navigation import unit_navigation_table

    return unit_navigation_table(ur.outcome.calibration.reps) if ur.calibrated else None


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
        # 1. the sessions, and the units to calibrate (new or changed)
        refs, path_errors, jobs, skipped = _plan_night(store, dataset, force, follow_symlinks)
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
        _STARTED_RUNS[str(results)] = (run_id, log)  # its outcome is recorded if the run fails
        # 2. calibrate them in batches, each lot stored as soon as its units are done
        night = _LotStorage(store, run_id, version, log, progress, jobs)
        t_cal = night.calibrate_and_store(jobs, batch_size, run_discovery, max_in_flight, runner) - t0
        lots = sorted(night.tally.lots | (set(store.lots()) if interrupted else set()))
        # the pages the fit phase and the lots' storing freed (in the task runner's and the
        # writer's malloc arenas), given back before flags and reports allocate theirs in
        # this thread's arena (flows.memory; docs/benchmarks.md)
        release_memory()
        # 3. the flags of every lot the run touched (and of those the pooled scales move)
        lot_flags, report_lots = reflag_after_update(store, lots, cfg)
        release_memory()
        # 4. the reports of those lots and of any whose report is missing or out of date
        reports, problems = _write_night_reports(store, results, report_lots, unit_reports)
        for p in problems:
            logger.warning(p)
        # 5. the run log's end; interrupted runs marked recovered
        log.update(
            {
                "end": iso(utc_now()),
                "elapsed_s": round(time.monotonic() - t0, 3),
                # the fit phase (read ... aggregate) until the last batch is back; the storing
                # of lots overlaps it (store_s: time spent storing, in the writer thread)
                "calibration_s": round(t_cal, 3),
                "store_s": round(night.store_s, 3),
                **night.tally.log_fields(),
                "flagged_units": sorted({f"{f.lot}/{f.unit}" for lf in lot_flags for f in lf.flags}),
                "flags": [lf.to_dict() for lf in lot_flags],
                "lots_touched": lots,
                "reports": reports,
                "report_problems": problems,
                "discovery_notes": sorted(night.tally.discovery_notes),
                "summary": None,
            }
        )
        log["outcome"] = "failures" if run_had_failures(log) else "ok"
        log["summary"] = summary_line(log)
        store.write_run(run_id, log)
        _STARTED_RUNS.pop(str(results), None)
        for rid in interrupted:  # recovered: later runs need not redo it
            doc = store.read_run(rid)
            doc.update({"interrupted": True, "recovered_by": run_id})
            store.write_run(rid, doc)
    return jsonable(log)


def _plan_night(
    store: ResultsStore, dataset: str, force: bool, follow_symlinks: bool
) -> tuple[list[SessionRef], list, list[UnitJob], list[tuple[str, str]]]:
    """(turntable sessions found, bad paths, units to calibrate, units unchanged): one plan
    (:func:`schemas.unit_plan.plan_unit_jobs`) over the turntable sessions and the field
    recordings (``lot=L/unit=U/field/``) against the store's fingerprints; the store's digest
    cache keeps the files of the dataset only."""
    refs, path_errors = find_sessions(dataset, follow_symlinks=follow_symlinks)
    field_refs, field_errors = find_field_recordings(dataset, follow_symlinks=follow_symlinks)
    digests = DigestCache(store.read_digest_cache())
    jobs, skipped, refused = plan_unit_jobs([*refs, *field_refs], store.fingerprints(), force, digests)
    path_errors = [*path_errors, *field_errors, *refused]
    for j in jobs:  # its noise recordings (schemas.noise_dataset) follow the same rule
        j.follow_symlinks = follow_symlinks
    current = {os.path.join(str(r.path), n) for r in refs for n in ("steps.parquet", "samples.parquet")}
    current |= {
        p for p in digests.entries if os.path.basename(os.path.dirname(p)) == "noise" and os.path.exists(p)
    }
    if digests.read or set(digests.entries) - current:  # files of moved datasets go
        store.write_digest_cache({p: e for p, e in digests.entries.items() if p in current})
    return refs, path_errors, jobs, skipped


class _LotStorage:
    """The calibration phase of a night: batches of units calibrated, the progress in the run
    log, and each lot stored as soon as its last unit is done, then dropped (memory: one lot,
    not the fleet; flags and reports wait for every lot: the robust scale is pooled)."""

    def __init__(
        self, store: ResultsStore, run_id: str, version: str, log: dict, progress: bool, jobs: list[UnitJob]
    ) -> None:
        self.store, self.run_id, self.version, self.log = store, run_id, version, log
        self.tally = RunTally()
        self.store_s = 0.0
        self.progress = _Progress(
            len(jobs), stream=sys.stderr if progress else False, per_lot=Counter(j.lot for j in jobs)
        )
        self._writes: deque = deque()
        self._writer: ThreadPoolExecutor | None = None

    def calibrate_and_store(
        self,
        jobs: list[UnitJob],
        batch_size: int,
        run_discovery: bool,
        max_in_flight: int,
        runner: str | None,
    ) -> float:
        """Returns when the last batch came back (time.monotonic; the lots' storing may
        finish after it)."""
        pooled = bool(jobs) and runner != "dask" and uses_unit_work_pool(runner, len(jobs))
        if not pooled:  # workers started while Prefect started, for a run that needs none
            discard_prestarted_workers()
        if not jobs:
            return time.monotonic()
        self.log["unit_work"] = "worker processes" if pooled else "task runner"
        with (
            ThreadPoolExecutor(1, thread_name_prefix="mimucal-store") as self._writer,
            unit_work_pool(None if runner == "dask" else runner, len(jobs) if pooled else 0),
        ):
            _run_batches(jobs, batch_size, run_discovery, self.on_progress, self.on_lot, max_in_flight)
            fitted = time.monotonic()
            while self._writes:
                self._writes.popleft().result()
        return fitted

    def on_progress(self, batch: list[UnitResult]) -> None:
        prog = self.progress
        line = prog.update(batch)
        self.log["progress"] = {
            "units_done": prog.done,
            "units_total": prog.total,
            "failed_sessions": prog.failed_sessions,
            "line": line,
        }
        self.store.write_run(self.run_id, self.log)

    def on_lot(self, lot: str, lot_results: list[UnitResult]) -> None:
        # the writing runs in one writer thread so that batches keep being submitted meanwhile
        # (with worker processes the workers would otherwise wait for it); at most one more
        # lot waits behind the one being written (memory: two lots), and a failed write fails
        # the run
        while len(self._writes) >= 2:
            self._writes.popleft().result()
        self._writes.append(self._writer.submit(self._store_lot, lot_results))

    def _store_lot(self, lot_results: list[UnitResult]) -> None:
        t = time.monotonic()
        self.tally.add(lot_results, store_results(self.store, lot_results, self.run_id, self.version))
        del lot_results[:]  # this thread's reference: the lot's results can go now
        release_memory()  # its frames' pages back before the next lot (flows.memory)
        self.store_s += time.monotonic() - t


def _write_night_reports(
    store: ResultsStore, results: str, report_lots: list[str], unit_reports: bool
) -> tuple[list[str], list[str]]:
    """:func:`write_reports` of the lots re-flagged and of those whose report is missing or
    older than their lot's tables (a run that died or hit a full disk while writing them);
    with ``unit_reports`` every unit of those lots too."""
    report_lots = sorted(set(report_lots) | set(reports_to_rebuild(store)))
    if not report_lots:
        return [], []
    units = (
        tuple(sorted({str(u) for u in store.read("units", lots=report_lots, columns=["unit"])["unit"]}))
        if unit_reports
        else ()
    )
    return write_reports(results, report_lots, units)


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


# the run log's ``outcome`` as the summary line says it
OUTCOME_WORDS = {"ok": "all ok", "failures": "some units failed", "run failed": "the run failed"}


def summary_line(log: dict, wall_s: float | None = None) -> str:
    """One line: the outcome ("all ok", "some units failed" (exit code 1) or "the run failed"
    (5)), units, sessions, flags; the flow's time, or ``wall_s`` (the command's wall time)
    with the flow's time in brackets."""
    outcome = OUTCOME_WORDS.get(log.get("outcome") or "", None)
    return (
        f"{log.get('kind', 'run')} {log['run_id']}: "
        + (f"{outcome}; " if outcome else "")
        + f"{log.get('units_found', '?')} units "
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
    "calib_core.noise",
    "flows.thermal_units",
    "calib_core.models.zhang2017",
    "calib_core.sim.navigation",
    "calib_core.models.pipeline",
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
        field_job = (
            None if refs else field_unit_job(dataset, unit, follow_symlinks)
        )  # a unit of field recordings
        if not refs and field_job is None:
            why = "; ".join(str(e) for e in path_errors) or "no session directory found"
            raise LookupError(
                f"unit {unit!r}: no session under {dataset} ({why}); {known_names(dataset, 'unit')}"
            )
        lot = refs[0].key.lot if refs else field_job.lot
        job = field_job or UnitJob(lot, unit, refs, "rerun", follow_symlinks=follow_symlinks)
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
        store.write_run(run_id, log)
        _STARTED_RUNS[str(results)] = (run_id, log)  # its outcome is recorded if the rerun fails
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
        log["outcome"] = "failures" if run_had_failures(log) else "ok"
        log["summary"] = summary_line(log)
        store.write_run(run_id, log)
        _STARTED_RUNS.pop(str(results), None)
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
    with _preloading(), _prestarted_workers_discarded():  # imports overlap the API server's start
        runtime.await_api_server()
        with runtime.run_settings(), _outcome_recorded(results):
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


@contextmanager
def _prestarted_workers_discarded():
    """Worker processes started for a run that ended (or failed) before adopting them are
    shut down with it, not left to the process's exit."""
    try:
        yield
    finally:
        discard_prestarted_workers()


# results root -> (run id, run log) of a nightly run started in this process and not ended
_STARTED_RUNS: dict[str, tuple[str, dict]] = {}


def run_had_failures(log: dict) -> bool:
    """Whether any session, unit or report of a run failed, or a directory did not parse
    (exit code 1; the run log's ``outcome`` is ``failures``)."""
    return bool(
        log.get("failed_sessions")
        or log.get("units_failed")
        or log.get("path_errors")
        or log.get("report_problems")
        or log.get("unit_errors")
    )


@contextmanager
def _outcome_recorded(results: str | Path):
    """A nightly run or rerun that raises after its run log was written gets ``outcome: "run
    failed"``, the error (one line) and a summary saying so in that log; it keeps no ``end``, so the next run
    recovers it (its flags and reports). Exit code 5 (flows.cli) tells it from "some units
    failed" (1)."""
    try:
        yield
    except Exception as exc:
        started = _STARTED_RUNS.pop(str(results), None)
        if started is not None:
            run_id, log = started
            log.update(
                {
                    "outcome": "run failed",
                    "failed_at": iso(utc_now()),
                    "error": f"{type(exc).__name__}: {exc}".splitlines()[0][:500],
                }
            )
            log["summary"] = summary_line(log)
            try:
                ResultsStore(Path(results)).write_run(run_id, log)
            except Exception:  # noqa: BLE001 - the run's own error is the one to report
                pass
        raise


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
    runtime.await_api_server()
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
    if (
        not refs and field_unit_job(dataset, unit, follow_symlinks) is None
    ):  # before Prefect: one line, no failed flow run
        why = "; ".join(str(e) for e in path_errors) or "no session directory found"
        raise LookupError(
            f"unit {unit!r}: no session under {dataset} ({why}); {known_names(dataset, 'unit')}"
        )
    with _preloading():  # the flow's imports overlap the API server's start
        runtime.await_api_server()
        with runtime.run_settings(), _outcome_recorded(results):
            return rerun_flow(
                str(dataset),
                str(results),
                unit,
                None if config is None else str(config),
                wait,
                run_discovery,
                follow_symlinks,
            )
