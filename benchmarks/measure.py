"""One measurement per process: ``python -m benchmarks.measure KIND [options]``.

Each measurement runs in its own process so that its peak resident memory is its own (the
parent, :mod:`benchmarks.run`, reads the child's ``ru_maxrss`` with ``os.wait4``) and so that
imports and Prefect start-up are counted where they belong. The child prints one line
``BENCH_RESULT {json}`` on stdout. Besides its own peak RSS, the child samples the RSS of its
whole process tree (Prefect's temporary API server, Dask workers, a process pool) every 0.1 s
with psutil and reports the peak of the sum as ``tree_peak_rss_mb``.

Kinds:

- ``simulate``: write a fleet with :func:`flows.fleet_sim.simulate_fleet`.
- ``floor``: a bare ``pyarrow.dataset`` scan of every ``samples.parquet`` with column
  projection (step + six sensor columns) and a group-by-step mean per file: the cost of just
  reading the data and averaging it.
- ``fit``: the nightly fit phase without Prefect: read, validate, average, fit, model
  discovery, aggregate (:func:`flows.unit_pipeline.calibrate_batch`, what a nightly task runs)
  over all units, in one process or a pool of ``--workers`` processes fed batches of units,
  then flag every lot (:func:`calib_core.outliers.flag_lots`); the floor is measured in the
  same process just before and just after (``floor_before``, ``floor_after``), so the ratio
  holds on a noisy machine. ``--no-discovery`` leaves discovery out.
- ``stages``: the same split into read+validate and average (per session), fit (a unit's
  repetitions together, as the nightly fits them), model discovery (diagnosis and the store's
  rows, also in CPU ms per unit) and aggregate, on the first ``--units`` units (where the fit
  phase time goes), after one untimed pass over the first unit (first-call imports); all in
  ms per session.
- ``nightly``: :func:`flows.nightly.nightly_fleet_calibration` end to end (``force=True``),
  with the local task runner ``--runner threads|processes`` (``--dask-workers 0``) or the
  ``dask`` runner with a ``LocalCluster`` of N single-threaded worker processes (started and
  warmed before the flow's body: ``cluster_start_s``, ``dask_warmup_s``); the run log gives the
  fit phase (``calibration_s``) and the rest (store, flags, reports); ``fit_phase_cpu_s`` is the
  CPU of the flow's process, its store-writer thread, the API server and the workers during
  the fit phase (:class:`CpuByRole`).
- ``rerun``: :func:`flows.nightly.rerun_unit` of one unit on an existing results store.
- ``unit``: :func:`flows.unit_pipeline.calibrate_unit` of one unit, no Prefect.
- ``prefect``: Prefect start-up: ``import prefect`` and a trivial flow run with mimucal's
  settings (a fresh ``PREFECT_HOME`` gives the first-run cost, an existing one the usual).
"""

from __future__ import annotations

import argparse
import importlib
import json
import os
import resource
import sys
import threading
import time
from pathlib import Path
from typing import TYPE_CHECKING

if TYPE_CHECKING:  # imports are measured: pandas only where a child needs it
    import pandas as pd

SENSOR_COLUMNS = ["gx", "gy", "gz", "ax", "ay", "az"]


class _SamplerThread:
    """A daemon thread that calls ``_sample`` every ``interval_s`` while the block runs, and
    once more at its end."""

    def __init__(self, interval_s: float):
        self.interval_s = interval_s
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)

    def _sample(self) -> None:
        raise NotImplementedError

    def _run(self) -> None:
        while not self._stop.is_set():
            self._sample()
            self._stop.wait(self.interval_s)

    def __enter__(self):
        self._thread.start()
        return self

    def __exit__(self, *exc):
        self._sample()
        self._stop.set()
        self._thread.join()
        return False


class TreeRss(_SamplerThread):
    """Peak of the summed RSS of this process and all its descendants, sampled."""

    def __init__(self, interval_s: float = 0.1):
        super().__init__(interval_s)
        self.peak = 0
        self.cpu: dict[int, float] = {}  # last CPU seconds seen per pid of the tree

    def _sample(self) -> None:
        import psutil

        try:
            me = psutil.Process()
            procs = [me] + me.children(recursive=True)
        except psutil.Error:
            return
        total = 0
        for p in procs:
            try:
                total += p.memory_info().rss
                t = p.cpu_times()
                self.cpu[p.pid] = t.user + t.system
            except psutil.Error:
                pass
        self.peak = max(self.peak, total)


class CpuByRole(_SamplerThread):
    """CPU seconds of this process tree by role, sampled every ``interval_s`` with a wall-clock
    time stamp, so that the CPU spent inside a window (the nightly fit phase) can be taken
    afterwards: ``flow`` (this process less its store-writer thread), ``writer`` (the flow's
    ``mimucal-store`` thread), ``api`` (Prefect's temporary API server), ``workers`` (Dask
    workers and nannies, process-pool workers: every other descendant)."""

    def __init__(self, interval_s: float = 0.25):
        super().__init__(interval_s)
        self._roles: dict[int, str] = {}
        self.samples: list[tuple[float, dict[str, float]]] = []
        self._last: dict[int, tuple[str, float]] = {}  # pid or "t<tid>" -> (role, cpu)

    def _sample(self) -> None:
        import psutil

        now = time.time()
        try:
            me = psutil.Process()
            kids = me.children(recursive=True)
            writer_tids = {t.native_id for t in threading.enumerate() if t.name.startswith("mimucal-store")}
            t = me.cpu_times()
            self._last[me.pid] = ("flow", t.user + t.system)
            for th in me.threads():
                if th.id in writer_tids:
                    self._last[f"t{th.id}"] = ("writer", th.user_time + th.system_time)
        except psutil.Error:
            return
        for p in kids:
            try:
                if p.pid not in self._roles:  # cmdline once per process: sampling stays cheap
                    self._roles[p.pid] = "api" if "prefect.server" in " ".join(p.cmdline()) else "workers"
                role = self._roles[p.pid]
                t = p.cpu_times()
                self._last[p.pid] = (role, t.user + t.system)
            except psutil.Error:
                pass  # gone: its last value stays
        roles: dict[str, float] = {}
        for role, cpu in self._last.values():
            roles[role] = roles.get(role, 0.0) + cpu
        roles["flow"] = roles.get("flow", 0.0) - roles.get("writer", 0.0)
        self.samples.append((now, roles))

    def window(self, t0: float, t1: float) -> dict[str, float]:
        """CPU seconds by role between the samples nearest the wall-clock times t0 and t1."""
        if not self.samples:
            return {}
        a = min(self.samples, key=lambda s: abs(s[0] - t0))[1]
        b = min(self.samples, key=lambda s: abs(s[0] - t1))[1]
        return {k: round(b.get(k, 0.0) - a.get(k, 0.0), 2) for k in sorted(set(a) | set(b))}


def cpu_s() -> float:
    """User + system CPU seconds of this process and its waited-for children: less sensitive
    than wall time to other work on a shared machine."""
    a = resource.getrusage(resource.RUSAGE_SELF)
    b = resource.getrusage(resource.RUSAGE_CHILDREN)
    return a.ru_utime + a.ru_stime + b.ru_utime + b.ru_stime


def _units(dataset: str):
    from schemas.dataset import find_sessions

    refs, errors = find_sessions(dataset)
    by_unit: dict[tuple[str, str], list] = {}
    for r in refs:
        by_unit.setdefault((r.key.lot, r.key.unit), []).append(r)
    return [by_unit[k] for k in sorted(by_unit)], errors


def _sample_files(dataset: str) -> list[str]:
    return sorted(str(p) for p in Path(dataset).glob("lot=*/unit=*/rep=*/samples.parquet"))


# --- kinds ------------------------------------------------------------------------------------
def do_simulate(a) -> dict:
    from calib_core.sim import protocols
    from flows.fleet_sim import simulate_fleet

    lots = max(1, -(-a.units // a.units_per_lot))
    per_lot = a.units // lots
    steps = protocols.default_session(duration_s=a.step_s)
    t0 = time.perf_counter()
    m = simulate_fleet(
        a.out, lots=lots, units=per_lot, reps=a.reps, seed=a.seed, sample_rate_hz=a.rate, protocol=steps
    )
    elapsed = time.perf_counter() - t0
    files = _sample_files(a.out)
    size = sum(os.path.getsize(p) for p in Path(a.out).rglob("*.parquet"))
    import pyarrow.parquet as pq

    rows = pq.ParquetFile(files[0]).metadata.num_rows
    return {
        "elapsed_s": elapsed,
        "lots": lots,
        "units": lots * per_lot,
        "reps": a.reps,
        "sessions": len(files),
        "n_steps": m["n_steps"],
        "samples_per_session": rows,
        "disk_mb": size / 1e6,
    }


def floor_scan(dataset: str) -> tuple[int, int]:
    """Scan + group-by-step mean of every session (one result table per file, so memory is
    bounded by a file). Returns (files, steps averaged)."""
    import pyarrow as pa
    import pyarrow.dataset as ds

    files = _sample_files(dataset)
    d = ds.dataset(files, format="parquet")
    n_steps = 0
    aggs = [(c, "mean") for c in SENSOR_COLUMNS]
    # scan_batches keeps pyarrow's threaded read-ahead across files; a session's samples come
    # in one or more batches tagged with their file, grouped when the file is complete
    pending: list = []
    current = None
    for tagged in d.scanner(
        columns=["step"] + SENSOR_COLUMNS, use_threads=True, batch_size=1 << 20
    ).scan_batches():
        path = tagged.fragment.path
        if current is not None and path != current:
            n_steps += pa.Table.from_batches(pending).group_by("step").aggregate(aggs).num_rows
            pending = []
        current = path
        pending.append(tagged.record_batch)
    if pending:
        n_steps += pa.Table.from_batches(pending).group_by("step").aggregate(aggs).num_rows
    return len(files), n_steps


def do_floor(a) -> dict:
    import pyarrow  # noqa: F401  (import cost is not part of the floor)
    import pyarrow.dataset  # noqa: F401

    t0, c0 = time.perf_counter(), cpu_s()
    n_files, n_steps = floor_scan(a.dataset)
    return {
        "elapsed_s": time.perf_counter() - t0,
        "cpu_s": cpu_s() - c0,
        "sessions": n_files,
        "steps": n_steps,
    }


SUMMARY_COLUMNS = ("lot", "unit", "model", "parameter", "mean", "std", "n_reps")


def _fit_units(batch: list, run_discovery: bool = True) -> tuple[pd.DataFrame, int, int, float]:
    """One batch of units as a nightly task calibrates them (read, validate, average, fit,
    model discovery, aggregate): :func:`flows.unit_pipeline.calibrate_batch`. Returns the
    units' summary rows (what flagging reads), sessions ok / failed, and CPU seconds."""
    import pandas as pd

    from flows.unit_pipeline import UnitJob, calibrate_batch

    c0 = time.process_time()
    jobs = [UnitJob(refs[0].key.lot, refs[0].key.unit, refs, "benchmark") for refs in batch]
    ok = failed = 0
    cols: dict[str, list] = {k: [] for k in SUMMARY_COLUMNS}
    for ur in calibrate_batch(jobs, run_discovery):
        ok += sum(s.succeeded for s in ur.outcome.sessions)
        failed += sum(not s.succeeded for s in ur.outcome.sessions)
        if ur.calibrated:
            for ps in ur.outcome.calibration.summary:
                for k, v in zip(
                    SUMMARY_COLUMNS, (ur.lot, ur.unit, ps.model, ps.name, ps.mean, ps.std, ps.n_reps)
                ):
                    cols[k].append(v)
    # one small frame per batch, as the flow holds the summary (a table read from the store),
    # not ~70 dicts per unit (30 KB per unit, which made the harness's peak grow with the fleet)
    return pd.DataFrame(cols), ok, failed, time.process_time() - c0


def _timed_floor(dataset: str) -> dict:
    t0, c0 = time.perf_counter(), cpu_s()
    n_files, n_steps = floor_scan(dataset)
    return {
        "elapsed_s": time.perf_counter() - t0,
        "cpu_s": cpu_s() - c0,
        "sessions": n_files,
        "steps": n_steps,
    }


def do_fit(a) -> dict:
    """The nightly fit phase without Prefect (read, validate, average, fit, discovery,
    aggregate, then flag every lot), with the floor measured in the same process just before
    and just after it, so that the ratio holds on a noisy machine."""
    import pandas as pd
    import pyarrow.dataset  # noqa: F401  (imports are part of neither)

    import calib_core.discovery  # noqa: F401
    import flows.unit_pipeline  # noqa: F401
    from calib_core.outliers import OutlierConfig, flag_lots
    from flows.compute_pool import PRELOAD

    # what the nightly's worker processes are forked with (flows.compute_pool's forkserver)
    for name in PRELOAD[1:]:
        importlib.import_module(name)
    if a.workers > 1:
        # the nightly's worker processes fork from its forkserver, which imports and warms,
        # and they start and warm themselves, while Prefect starts
        # (flows.task_runners.prestart_unit_work_pool): ready before the fit phase, so
        # started and waited for here, outside it
        from flows.compute_pool import prestart_workers, wait_for_forkserver, wait_for_prestarted_workers

        wait_for_forkserver()
        prestart_workers(a.workers)
        wait_for_prestarted_workers()
    units, _ = _units(a.dataset)
    # --no-floor: the floor's scan (pyarrow's threaded read-ahead and memory pool) raises this
    # process's peak RSS with the fleet size; the fit phase's own peak needs a run without it
    floor_before = _timed_floor(a.dataset) if a.floor else None
    t0, c0 = time.perf_counter(), cpu_s()
    ok = failed = 0
    frames: list = []  # each batch's summary rows
    worker_cpu = []
    if a.workers <= 1:
        # batch by batch, as a nightly task: calibrate_batch returns its whole batch's
        # results, so one call over the fleet would hold every unit's (~0.4 MB each) at once
        # and the peak would grow with the fleet for the harness's sake, not the pipeline's
        from schemas.unit_plan import make_batches

        c = 0.0
        for batch in make_batches(units, a.batch):
            b_summary, b_ok, b_failed, b_c = _fit_units(batch, a.discovery)
            frames.append(b_summary)
            ok, failed, c = ok + b_ok, failed + b_failed, c + b_c
        worker_cpu.append(c)
    else:
        from functools import partial

        from flows.compute_pool import compute_pool
        from schemas.unit_plan import make_batches

        batches = make_batches(units, a.batch)  # as the nightly cuts them
        # the nightly's pool: the workers started above (forked from the forkserver: numerics
        # imported, warmed, objects frozen; warmed again after the fork), one BLAS thread
        # each, no Arrow decoding threads
        with compute_pool(a.workers) as pool:
            for r, o, f, c in pool.map(partial(_fit_units, run_discovery=a.discovery), batches):
                frames.append(r)
                ok += o
                failed += f
                worker_cpu.append(c)
    t_cal, c_cal = time.perf_counter() - t0, cpu_s() - c0
    t1, c1 = time.perf_counter(), cpu_s()
    summary = pd.concat(frames, ignore_index=True) if frames else pd.DataFrame()
    del frames
    flags = flag_lots(summary, OutlierConfig()) if len(summary) else []
    t_flag, c_flag = time.perf_counter() - t1, cpu_s() - c1
    elapsed, cpu = time.perf_counter() - t0, cpu_s() - c0
    floor_after = _timed_floor(a.dataset) if a.floor else None
    floor = (
        min((floor_before, floor_after), key=lambda f: f["cpu_s"])
        if a.floor
        else {"cpu_s": None, "elapsed_s": None}
    )
    n = max(1, len(units))
    return {
        "elapsed_s": elapsed,
        "cpu_s": cpu,
        "per_unit_cpu_ms": 1e3 * cpu / n,
        "per_unit_ms": 1e3 * elapsed / n,
        "units": len(units),
        "sessions_ok": ok,
        "sessions_failed": failed,
        "workers": a.workers,
        "discovery": a.discovery,
        "calibrate_s": t_cal,
        "calibrate_cpu_s": c_cal,
        "flag_s": t_flag,
        "flag_cpu_s": c_flag,
        "worker_cpu_s": sum(worker_cpu),
        "flagged_units": len({(f.lot, f.unit) for lf in flags for f in lf.flags}),
        "floor_before": floor_before,
        "floor_after": floor_after,
        "floor_cpu_s": floor["cpu_s"],
        "floor_s": min(floor_before["elapsed_s"], floor_after["elapsed_s"]) if a.floor else None,
        "fit_vs_floor_cpu": cpu / floor["cpu_s"] if floor["cpu_s"] else None,
    }


def do_stages(a) -> dict:
    from calib_core.discovery import diagnose_unit
    from calib_core.discovery.presentation import finding_rows
    from calib_core.models.pipeline import calibrate_repetitions
    from flows.memory import keep_freed_memory
    from flows.noise_units import apply_noise
    from flows.unit_pipeline import aggregate_unit, calibrate_sessions
    from schemas.averaging import average_session
    from schemas.reader import read_session

    keep_freed_memory()  # as the nightly's calibrate_batch
    # as the nightly's workers are forked: warmed on a simulated unit, then gc.freeze()
    import flows.worker_warmup  # noqa: F401

    units, _ = _units(a.dataset)
    units = units[: a.units]
    t = {
        "read_validate": 0.0,
        "average": 0.0,
        "fit": 0.0,
        "discovery": 0.0,
        "aggregate": 0.0,
        "noise": 0.0,
        "floor": 0.0,
    }
    n, discovery_cpu, noise_cpu = 0, 0.0, 0.0
    import pyarrow.dataset as ds

    aggs = [(c, "mean") for c in SENSOR_COLUMNS]
    if units:  # one untimed pass first: the numerics' first-call imports are not a stage's
        outcomes = calibrate_sessions(units[0], keep_step_means=False, keep_static_steps=True)
        diagnose_unit([average_session(read_session(ref))[0] for ref in units[0]], tables=False)
        ref0 = units[0][0]
        apply_noise(aggregate_unit(ref0.key.lot, ref0.key.unit, outcomes), ref0.path.parent)
    for refs in units:
        sms = []
        for ref in refs:
            t0 = time.perf_counter()
            ds.dataset(str(ref.samples_path), format="parquet").to_table(
                columns=["step"] + SENSOR_COLUMNS
            ).group_by("step").aggregate(aggs)
            t1 = time.perf_counter()
            data = read_session(ref)
            t2 = time.perf_counter()
            sm, _ = average_session(data)
            t3 = time.perf_counter()
            sms.append(sm)
            t["floor"] += t1 - t0
            t["read_validate"] += t2 - t1
            t["average"] += t3 - t2
            n += 1
        # The repetitions of a unit are fitted together, as the nightly fits them.
        t0 = time.perf_counter()
        calibrate_repetitions(sms)
        t["fit"] += time.perf_counter() - t0
        # model discovery as the nightly runs it (diagnosis and the store's rows), CPU and wall
        t0, c0 = time.perf_counter(), time.process_time()
        finding_rows(diagnose_unit(sms, tables=False))
        t["discovery"] += time.perf_counter() - t0
        discovery_cpu += time.process_time() - c0
        outcomes = calibrate_sessions(refs, keep_step_means=False, keep_static_steps=True)
        t1 = time.perf_counter()
        unit_out = aggregate_unit(refs[0].key.lot, refs[0].key.unit, outcomes)
        t["aggregate"] += time.perf_counter() - t1
        # the unit's noise model on the static steps kept from its read, as the nightly
        t1, c1 = time.perf_counter(), time.process_time()
        apply_noise(unit_out, refs[0].path.parent)
        t["noise"] += time.perf_counter() - t1
        noise_cpu += time.process_time() - c1
    # per session: the unit-level fit, discovery and aggregate are spread over its sessions
    per_session_ms = {k: 1e3 * v / max(1, n) for k, v in t.items()}
    return {
        "sessions": n,
        "units": len(units),
        "per_session_ms": per_session_ms,
        "discovery_ms_per_unit": 1e3 * t["discovery"] / max(1, len(units)),
        "discovery_cpu_ms_per_unit": 1e3 * discovery_cpu / max(1, len(units)),
        "noise_cpu_ms_per_unit": 1e3 * noise_cpu / max(1, len(units)),
    }


def _prefect_env(results: str) -> None:
    from flows import runtime

    runtime.ensure_environment(results)


def do_nightly(a) -> dict:
    _prefect_env(a.results)
    os.environ["MIMUCAL_TASK_RUNNER"] = a.runner  # read by flows.task_runners.make_task_runner
    t_imp = time.perf_counter()
    from flows import nightly

    import_s = time.perf_counter() - t_imp
    if a.dask_workers > 0:
        # the dask runner as a nightly run uses it: its LocalCluster of N workers is started,
        # and warmed, by the flow's task runner before the flow's body (outside the fit phase;
        # its times are reported below, from flows.compute_pool.last_dask_startup)
        import logging

        logging.getLogger("distributed").setLevel(logging.WARNING)
        os.environ["MIMUCAL_TASK_RUNNER"] = "dask"
        os.environ["MIMUCAL_DASK_WORKERS"] = str(a.dask_workers)
    with CpuByRole() as roles:
        t0 = time.perf_counter()
        log = nightly.nightly_fleet_calibration(
            a.dataset, a.results, force=True, batch_size=a.batch, progress=False
        )
        wall = time.perf_counter() - t0
    fit = float(log.get("calibration_s") or 0.0)
    inflow = float(log.get("elapsed_s") or 0.0)
    out = {
        "wall_s": wall,
        "import_s": import_s,
        "cluster_start_s": 0.0,
        "flow_elapsed_s": inflow,
        "fit_phase_s": fit,
        "report_phase_s": inflow - fit,
        "outside_flow_s": wall - inflow,
        "units_calibrated": log.get("units_calibrated"),
        "sessions_calibrated": log.get("sessions_calibrated"),
        "failed_sessions": len(log.get("failed_sessions") or []),
        "reports": len(log.get("reports") or []),
        "report_problems": log.get("report_problems") or [],
        "dask_workers": a.dask_workers,
        "runner": "dask" if a.dask_workers else a.runner,
        "unit_work": log.get("unit_work"),
        "store_s": log.get("store_s"),
        "batch_size": a.batch,
    }
    if log.get("start"):  # CPU by role during the fit phase (wall-clock window of the log)
        from datetime import datetime

        t_start = datetime.fromisoformat(str(log["start"]).replace("Z", "+00:00")).timestamp()
        out["fit_phase_cpu_s"] = roles.window(t_start, t_start + fit)
    if a.dask_workers > 0:
        from flows.compute_pool import last_dask_startup

        out["cluster_start_s"] = last_dask_startup.get("cluster_start_s") or 0.0
        out["dask_warmup_s"] = last_dask_startup.get("warmup_s")
        out["dask_workers_seen"] = last_dask_startup.get("workers")
    return out


def do_rerun(a) -> dict:
    _prefect_env(a.results)
    t_imp = time.perf_counter()
    from flows import nightly

    import_s = time.perf_counter() - t_imp
    t0 = time.perf_counter()
    log = nightly.rerun_unit(a.dataset, a.results, a.unit)
    wall = time.perf_counter() - t0
    return {
        "wall_s": wall,
        "import_s": import_s,
        "flow_elapsed_s": float(log["elapsed_s"]),
        "outside_flow_s": wall - float(log["elapsed_s"]),
        "units_calibrated": log.get("units_calibrated"),
        "phases_s": log.get("phases_s"),
        "report_problems": log.get("report_problems") or [],
    }


def do_unit(a) -> dict:
    t_imp = time.perf_counter()
    from flows.unit_pipeline import calibrate_unit
    from schemas.dataset import find_sessions

    import_s = time.perf_counter() - t_imp
    t0 = time.perf_counter()
    refs, _ = find_sessions(a.dataset, unit=a.unit)
    u = calibrate_unit(refs)
    return {
        "elapsed_s": time.perf_counter() - t0,
        "import_s": import_s,
        "sessions_ok": sum(s.succeeded for s in u.sessions),
    }


def do_prefect(a) -> dict:
    _prefect_env(a.results)
    t0 = time.perf_counter()
    from prefect import flow

    from flows import runtime

    import_s = time.perf_counter() - t0

    @flow(name="mimucal-bench-noop", persist_result=False)
    def noop() -> int:
        return 1

    t1 = time.perf_counter()
    with runtime.run_settings():
        noop()
    first = time.perf_counter() - t1
    t2 = time.perf_counter()
    with runtime.run_settings():
        noop()
    second = time.perf_counter() - t2
    return {
        "import_s": import_s,
        "first_flow_s": first,
        "second_flow_s": second,
        "startup_s": import_s + first,
    }


KINDS = {
    "simulate": do_simulate,
    "floor": do_floor,
    "fit": do_fit,
    "stages": do_stages,
    "nightly": do_nightly,
    "rerun": do_rerun,
    "unit": do_unit,
    "prefect": do_prefect,
}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description="one benchmark measurement (see module docstring)")
    ap.add_argument("kind", choices=sorted(KINDS))
    ap.add_argument("--dataset")
    ap.add_argument("--results")
    ap.add_argument("--out")
    ap.add_argument("--unit")
    ap.add_argument("--units", type=int, default=10)
    ap.add_argument("--units-per-lot", type=int, default=50)
    ap.add_argument("--reps", type=int, default=5)
    ap.add_argument("--rate", type=float, default=100.0)
    ap.add_argument("--step-s", type=float, default=3.0)
    ap.add_argument("--seed", type=int, default=7)
    ap.add_argument("--workers", type=int, default=1)
    ap.add_argument("--batch", type=int, default=8)
    ap.add_argument("--dask-workers", type=int, default=0)
    ap.add_argument(
        "--runner",
        default="threads",
        choices=["auto", "threads", "processes", "prefect-processes"],
        help="nightly: the local task runner (flows.task_runners) when no Dask",
    )
    ap.add_argument(
        "--no-floor",
        dest="floor",
        action="store_false",
        help="fit: do not measure the floor in the same process (its peak RSS)",
    )
    ap.add_argument(
        "--no-discovery",
        dest="discovery",
        action="store_false",
        help="fit: leave model discovery out (the fit phase before issue 7)",
    )
    a = ap.parse_args(argv)
    with TreeRss() as tree:
        out = KINDS[a.kind](a)
    out["tree_peak_rss_mb"] = tree.peak / 2**20
    out["tree_cpu_s"] = sum(tree.cpu.values())  # children sampled every 0.1 s: a lower bound
    out["process_cpu_s"] = cpu_s()
    out["self_peak_rss_mb"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    out["children_peak_rss_mb"] = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss / 1024
    sys.stdout.flush()
    print("BENCH_RESULT " + json.dumps(out), flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
