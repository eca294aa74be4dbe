"""The unit pipeline run once on a simulated unit, in a process that workers are forked
from, so that every worker starts warm; and once more in a worker just forked, before its
first batch, when the pool is started ahead of the work.

A process's first unit costs more than a later one: Parquet's reader, threadpoolctl's
library scan, the models imported on first use and NumPy's first calls are paid once per
process. A worker forked after this has them already. It still pays, over its first batch,
the first writes to the pages it shares with its parent (copy on write: reference counts,
the allocators' and libraries' caches); :func:`warm_forked_worker` pays them at the worker's
start instead, which a pool started while Prefect starts (flows.compute_pool.prestart_workers)
takes out of the fit phase. Importing the module does the first warm-up
(:func:`warm_unit_pipeline`), because a ``multiprocessing`` forkserver can only be given
modules to import (:data:`flows.compute_pool.PRELOAD` names it last); importing it again does
nothing. It then moves every object alive to the collector's permanent generation
(``gc.freeze``).
"""

from __future__ import annotations

import gc
import tempfile
import time
from pathlib import Path

warm_up_s: float | None = None  # how long the warm-up took in this process (None: not run)
warm_up_error: str | None = None  # why it did not complete, if it did not
forked_warm_up_s: float | None = None  # how long warm_forked_worker took (None: not run)
# the simulated unit's files (path under the fleet root -> bytes), kept for the forked workers
_unit_files: dict[str, bytes] = {}


def _calibrate_simulated_unit(root: str) -> str | None:
    """Calibrate the one unit under ``root`` as a nightly task does (no BLAS or Arrow thread
    pool started: the process forks workers afterwards); why it did not calibrate, if not."""
    from threadpoolctl import threadpool_limits

    from flows.unit_pipeline import calibrate_batch
    from schemas import reader
    from schemas.dataset import find_sessions
    from schemas.unit_plan import UnitJob

    arrow_threads = reader._arrow_threads
    reader.use_arrow_threads(False)
    try:
        with threadpool_limits(1):
            refs, _ = find_sessions(root)
            (result,) = calibrate_batch([UnitJob(refs[0].key.lot, refs[0].key.unit, refs, "warm-up")])
    finally:
        reader.use_arrow_threads(arrow_threads)
    if result.diagnosis is None or result.outcome.calibration is None:
        return f"the simulated unit did not calibrate: {result.discovery_note}"
    return None


def warm_unit_pipeline() -> float:
    """Simulate one unit of the default protocol (5 repetitions at 100 Hz: the buffers and
    shapes of a production unit) in a temporary directory and run
    :func:`flows.unit_pipeline.calibrate_batch` on it, model discovery and the noise model
    included, as a nightly task does; returns the seconds it took (once per process: later
    calls return the first figure). The unit's files are kept in memory for
    :func:`warm_forked_worker`. A failure is not an error: the workers then warm on their
    first unit, as without this module."""
    global warm_up_s, warm_up_error
    if warm_up_s is not None:
        return warm_up_s
    t0 = time.perf_counter()
    try:
        from flows.fleet_sim import simulate_fleet

        with tempfile.TemporaryDirectory(prefix="mimucal-warm-") as d:
            simulate_fleet(d, lots=1, units=1, reps=5, seed=0, sample_rate_hz=100.0)
            files = {str(p.relative_to(d)): p.read_bytes() for p in Path(d).rglob("*") if p.is_file()}
            warm_up_error = _calibrate_simulated_unit(d)
        if warm_up_error is None:
            _unit_files.update(files)
    except Exception as exc:  # noqa: BLE001 - warming is an optimisation, never a failure
        warm_up_error = f"{type(exc).__name__}: {exc}"
    warm_up_s = time.perf_counter() - t0
    return warm_up_s


def warm_forked_worker() -> float | None:
    """In a worker forked from a warmed process: calibrate the same simulated unit once more,
    so that the worker's first real batch does not pay the first writes to the pages it
    shares with its parent. Returns the seconds it took, None when there is nothing to do
    (the parent's warm-up did not run or failed). Never raises."""
    global forked_warm_up_s
    if not _unit_files:
        return None
    t0 = time.perf_counter()
    try:
        with tempfile.TemporaryDirectory(prefix="mimucal-warm-") as d:
            for rel, data in _unit_files.items():
                path = Path(d, rel)
                path.parent.mkdir(parents=True, exist_ok=True)
                path.write_bytes(data)
            _calibrate_simulated_unit(d)
    except Exception:  # noqa: BLE001 - warming is an optimisation, never a failure
        return None
    forked_warm_up_s = time.perf_counter() - t0
    return forked_warm_up_s


warm_unit_pipeline()
# What is alive now (the imported modules, their tables, the warm-up's caches) lives as long
# as the process: the permanent generation keeps the collector's full passes from walking it
# again and again, and a forked worker from writing to those pages
gc.freeze()
