"""Worker processes for the CPU-bound unit work of one flow run (the ``processes`` runner).

The unit work (read, average, fit, discovery) is Python and numpy on small arrays: it holds
the GIL, so Prefect's thread pool runs it on one core. Prefect's own ``ProcessPoolTaskRunner``
uses both cores but each spawned worker imports Prefect and builds its own client and task
context before its first task (8-10 s of CPU per worker on these machines,
docs/perf-parallel.md), which only pays on fleets of several hundred units.

Here the Prefect tasks stay where they are (one task run per batch of units in the flow's
thread pool, with its state and logs as with ``threads``); each task hands its batch to a pool
of processes forked from a *forkserver* that has imported the numerics once (numpy, pandas,
pyarrow, scipy, calib_core, schemas; not Prefect). A worker is a fork of that clean,
thread-free server: it starts in ~0.1 s, never talks to Prefect, and sends back the batch's
results (pickled: ~0.1 MB per unit).

A worker that dies (killed, out of memory) breaks the pool; the batch is then run again in the
flow's process, so a crash costs time, never a unit (``run_in_pool``).
"""
from __future__ import annotations

import logging
import multiprocessing as mp
import threading
from concurrent.futures import ProcessPoolExecutor
from concurrent.futures.process import BrokenProcessPool
from contextlib import contextmanager
from typing import Any, Callable, Iterator

# imported once by the forkserver; every worker is a fork of it
PRELOAD = ("__main__", "flows.unit_pipeline", "calib_core.discovery", "calib_core.outliers")

_log = logging.getLogger(__name__)
_lock = threading.Lock()
_pool: ProcessPoolExecutor | None = None
_broken = False


def _init_worker() -> None:
    # one BLAS thread per worker: two workers on two cores must not each start a pool of two
    # (flows.task_runners.limit_worker_threads does the same, but referencing it would make
    # every worker import that module and with it Prefect, which these workers never need)
    try:
        from threadpoolctl import threadpool_limits
        threadpool_limits(1)
    except Exception:  # pragma: no cover - threadpoolctl is a dependency
        pass


@contextmanager
def compute_pool(workers: int) -> Iterator[ProcessPoolExecutor]:
    """A pool of ``workers`` processes that :func:`run_in_pool` uses while the block runs."""
    global _pool, _broken
    ctx = mp.get_context("forkserver")
    ctx.set_forkserver_preload(list(PRELOAD))
    pool = ProcessPoolExecutor(max_workers=max(1, int(workers)), mp_context=ctx,
                               initializer=_init_worker)
    with _lock:
        previous, _pool, _broken = _pool, pool, False
    try:
        yield pool
    finally:
        with _lock:
            _pool = previous
        pool.shutdown(wait=True, cancel_futures=True)


def active() -> bool:
    return _pool is not None


def run_in_pool(fn: Callable[..., Any], *args: Any) -> Any:
    """``fn(*args)`` in the current pool when a flow opened one, else in this process. ``fn``
    and its arguments must be picklable (module-level function, plain data)."""
    global _broken
    pool = _pool
    if pool is None or _broken:
        return fn(*args)
    try:
        return pool.submit(fn, *args).result()
    except BrokenProcessPool as exc:
        with _lock:
            _broken = True
        _log.warning("compute pool broken (%s); running the remaining batches in the flow's "
                     "process", exc)
        return fn(*args)
