"""The unit pipeline run once on a simulated unit, in a process that workers are forked
from, so that every worker starts warm.

A process's first unit costs more than a later one: Parquet's reader, threadpoolctl's
library scan, the models imported on first use and NumPy's first calls are paid once per
process. A worker forked after this has them already (it still pays the first writes to the
pages it shares with its parent). Importing the module does the
warm-up (:func:`warm_unit_pipeline`), because a ``multiprocessing`` forkserver can only be
given modules to import (:data:`flows.compute_pool.PRELOAD` names it last); importing it
again does nothing. It then moves every object alive to the collector's permanent generation
(``gc.freeze``).
"""

from __future__ import annotations

import gc
import tempfile
import time

warm_up_s: float | None = None  # how long the warm-up took in this process (None: not run)
warm_up_error: str | None = None  # why it did not complete, if it did not


def warm_unit_pipeline() -> float:
    """Simulate one unit of the default protocol (5 repetitions at 100 Hz: the buffers and
    shapes of a production unit) in a temporary directory and run
    :func:`flows.unit_pipeline.calibrate_batch` on it, model discovery and the noise model
    included, as a nightly task does; returns the seconds it took (once per process: later
    calls return the first figure). A failure is not an error: the workers then warm on
    their first unit, as without this module."""
    global warm_up_s, warm_up_error
    if warm_up_s is not None:
        return warm_up_s
    t0 = time.perf_counter()
    try:
        from threadpoolctl import threadpool_limits

        from flows.fleet_sim import simulate_fleet
        from flows.unit_pipeline import calibrate_batch
        from schemas import reader
        from schemas.dataset import find_sessions
        from schemas.unit_plan import UnitJob

        # no BLAS or Arrow thread pool is started here: the process forks workers afterwards
        arrow_threads = reader._arrow_threads
        reader.use_arrow_threads(False)
        try:
            with threadpool_limits(1), tempfile.TemporaryDirectory(prefix="mimucal-warm-") as d:
                simulate_fleet(d, lots=1, units=1, reps=5, seed=0, sample_rate_hz=100.0)
                refs, _ = find_sessions(d)
                (result,) = calibrate_batch([UnitJob(refs[0].key.lot, refs[0].key.unit, refs, "warm-up")])
                if result.diagnosis is None or result.outcome.calibration is None:
                    warm_up_error = f"the simulated unit did not calibrate: {result.discovery_note}"
        finally:
            reader.use_arrow_threads(arrow_threads)
    except Exception as exc:  # noqa: BLE001 - warming is an optimisation, never a failure
        warm_up_error = f"{type(exc).__name__}: {exc}"
    warm_up_s = time.perf_counter() - t0
    return warm_up_s


warm_unit_pipeline()
# What is alive now (the imported modules, their tables, the warm-up's caches) lives as long
# as the process: the permanent generation keeps the collector's full passes from walking it
# again and again, and a forked worker from writing to those pages
gc.freeze()
