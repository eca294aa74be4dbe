"""Worker processes for the CPU-bound unit work of one flow run (the ``processes`` runner).

The unit work (read, average, fit, discovery) is Python and numpy on small arrays: it holds
the GIL, so Prefect's thread pool runs it on one core. Prefect's own ``ProcessPoolTaskRunner``
uses both cores but each spawned worker imports Prefect and builds its own client and task
context before its first task (8-10 s of CPU per worker on these machines,
docs/benchmarks.md), which only pays on fleets of several hundred units.

Here the Prefect tasks stay where they are (one task run per batch of units in the flow's
thread pool, with its state and logs as with ``threads``); each task hands its batch to a pool
of processes forked from a *forkserver* that has imported the numerics once (numpy, pandas,
pyarrow, scipy, calib_core, schemas; not Prefect). A worker is a fork of that clean,
thread-free server: it starts in ~0.1 s, never talks to Prefect, and sends back the batch's
results (pickled: ~0.1 MB per unit). The forkserver itself takes ~1 s to import the numerics,
and the first worker waits for it: :func:`start_forkserver` starts it early (the nightly
launcher before Prefect starts, a served run at the top of its body), and
:func:`prestart_workers` forks the workers then too, each running the unit pipeline once more
on a simulated unit before the pool that adopts them gets its first batch. Workers read their
sessions without Arrow's decoding threads: the two of them already keep both cores busy.

A worker that dies (killed, out of memory) breaks the pool; the batch is then run again in the
flow's process, so a crash costs time, never a unit (``run_in_pool``).

The ``dask`` runner uses the same arrangement with a Dask cluster as the pool
(:func:`dask_pool`): a local ``LocalCluster`` of single-threaded worker processes, or the
scheduler at an address. Its workers run only the batch function (no Prefect, no task context,
no API traffic) and are warmed before the flow's fit phase starts (the numerics imported once
per worker: :data:`PRELOAD`); the start-up and warm-up times are kept in :data:`last_dask_startup`.
A Dask worker that dies is replaced (nanny) and the scheduler runs its batch again elsewhere;
a batch that keeps killing workers (``KilledWorker``) or a lost scheduler runs in the flow's
process instead, as above.
"""

from __future__ import annotations

import logging
import multiprocessing as mp
import threading
import time
from collections.abc import Callable, Iterator
from concurrent.futures import CancelledError, ProcessPoolExecutor, ThreadPoolExecutor
from concurrent.futures.process import BrokenProcessPool
from contextlib import contextmanager
from typing import Any

# imported once by the forkserver; every worker is a fork of it (the noise analysis and the
# thermal fit are imported on a worker's first unit otherwise). The last one runs the unit
# pipeline once on a tiny simulated unit (flows.worker_warmup): the first-call costs a
# worker would otherwise pay on its first unit
PRELOAD = (
    "__main__",
    "flows.unit_pipeline",
    "calib_core.discovery",
    "calib_core.outliers",
    "calib_core.noise",
    "flows.thermal_units",
    "flows.worker_warmup",
)
WARM_UP = "flows.worker_warmup"

_log = logging.getLogger(__name__)
_lock = threading.Lock()
_pool: ProcessPoolExecutor | DaskPool | None = None
_broken = False
# how long the last dask_pool took to start (cluster_start_s: a LocalCluster; connect_s: the
# client; warmup_s: the workers' imports) and how many workers it had
last_dask_startup: dict[str, Any] = {}


def _init_worker(warm: bool = False) -> None:
    """A worker's start: one BLAS thread, no Arrow decoding threads; ``warm``: the unit
    pipeline run once more in this fork (flows.worker_warmup.warm_forked_worker), for a pool
    started ahead of its work (:func:`prestart_workers`)."""
    # one BLAS thread per worker: two workers on two cores must not each start a pool of two
    # (flows.task_runners.limit_worker_threads does the same, but referencing it would make
    # every worker import that module and with it Prefect, which these workers never need)
    try:
        from threadpoolctl import threadpool_limits

        threadpool_limits(1)
    except Exception:  # pragma: no cover - threadpoolctl is a dependency
        pass
    # nor Arrow's decoding threads (the forkserver imported the reader already)
    from schemas.reader import use_arrow_threads

    use_arrow_threads(False)
    if warm:
        from flows.worker_warmup import warm_forked_worker

        warm_forked_worker()


@contextmanager
def _active(pool: ProcessPoolExecutor | DaskPool) -> Iterator[None]:
    """Make ``pool`` the one :func:`run_in_pool` uses while the block runs (and not broken);
    the previous one is active again afterwards."""
    global _pool, _broken
    with _lock:
        previous, _pool, _broken = _pool, pool, False
    try:
        yield
    finally:
        with _lock:
            _pool = previous


def _forkserver_context() -> mp.context.ForkServerContext:
    ctx = mp.get_context("forkserver")
    ctx.set_forkserver_preload(list(PRELOAD))
    return ctx


def start_forkserver() -> None:
    """Start the forkserver the workers are forked from, if it is not running (one per
    process, shared by every pool). It imports :data:`PRELOAD` in its own process (~1 s of
    CPU) and the first worker waits for that: a flow's launcher calls this before Prefect
    starts, so that the imports run while Prefect starts its API server, not in the fit
    phase before the first batch (flows.task_runners.prestart_unit_work_pool)."""
    from multiprocessing import forkserver

    _forkserver_context()
    forkserver.ensure_running()


def _noop() -> None:
    return None


def wait_for_forkserver() -> None:
    """Start the forkserver if needed and return once it has imported :data:`PRELOAD` and
    warmed (one throwaway child is forked from it and joined): what Prefect's start-up gives
    the nightly before its fit phase, for a caller that has no such wait to hide it in (the
    benchmark's fit phase)."""
    start_forkserver()
    child = _forkserver_context().Process(target=_noop)
    child.start()
    child.join()


def _new_pool(workers: int, warm: bool) -> ProcessPoolExecutor:
    return ProcessPoolExecutor(
        max_workers=workers,
        mp_context=_forkserver_context(),
        initializer=_init_worker,
        initargs=(warm,),
    )


# a pool whose workers were started ahead of the work (prestart_workers), waiting for the
# compute_pool that adopts it: (pool, workers, the calls that started them)
_prestarted: tuple[ProcessPoolExecutor, int, list] | None = None
_exit_hook = False  # discard_prestarted_workers registered to run at the process's exit


def prestart_workers(workers: int) -> bool:
    """Start ``workers`` worker processes now, each warmed after its fork
    (flows.worker_warmup.warm_forked_worker), for the next :func:`compute_pool` of that size
    to adopt: the nightly launcher calls this while Prefect starts, so that neither the forks
    nor a worker's first-batch costs fall in the fit phase. A pool that no flow adopts is
    shut down by :func:`discard_prestarted_workers` (the nightly calls it once its fit phase
    is over) or at the process's exit. Returns whether workers were started (not if some
    are waiting already)."""
    global _prestarted, _exit_hook
    workers = max(1, int(workers))
    with _lock:
        if _prestarted is not None:
            return False
        pool = _new_pool(workers, warm=True)
        try:
            # ProcessPoolExecutor forks a worker for each call submitted while none is idle:
            # one call per worker starts them all now
            _prestarted = (pool, workers, [pool.submit(_noop) for _ in range(workers)])
        except Exception as exc:  # noqa: BLE001 - starting early is an optimisation
            pool.shutdown(wait=False, cancel_futures=True)
            _log.warning("worker processes not started ahead (%s); the fit phase starts them", exc)
            return False
        if not _exit_hook:
            import atexit

            atexit.register(discard_prestarted_workers)
            _exit_hook = True
    return True


def wait_for_prestarted_workers(timeout: float | None = None) -> bool:
    """Wait until the prestarted workers have started and warmed; whether there are any."""
    from concurrent.futures import wait

    prestarted = _prestarted
    if prestarted is None:
        return False
    wait(prestarted[2], timeout=timeout)
    return True


def discard_prestarted_workers() -> None:
    """Shut down the prestarted workers if no :func:`compute_pool` adopted them (a run with
    nothing to calibrate in worker processes); a no-op otherwise."""
    global _prestarted
    with _lock:
        prestarted, _prestarted = _prestarted, None
    if prestarted is not None:
        prestarted[0].shutdown(wait=True, cancel_futures=True)


def _adopt_prestarted(workers: int) -> ProcessPoolExecutor | None:
    """The prestarted pool if it has ``workers`` workers and none has died (it is then no
    longer prestarted); any other is shut down."""
    global _prestarted
    with _lock:
        prestarted, _prestarted = _prestarted, None
    if prestarted is None:
        return None
    pool, n, started = prestarted
    if n == workers and not any(f.done() and f.exception() is not None for f in started):
        return pool
    pool.shutdown(wait=True, cancel_futures=True)
    return None


@contextmanager
def compute_pool(workers: int) -> Iterator[ProcessPoolExecutor]:
    """A pool of ``workers`` processes that :func:`run_in_pool` uses while the block runs:
    the prestarted one (:func:`prestart_workers`) if it has that many, else new ones."""
    workers = max(1, int(workers))
    pool = _adopt_prestarted(workers) or _new_pool(workers, warm=False)
    try:
        with _active(pool):
            yield pool
    finally:
        pool.shutdown(wait=True, cancel_futures=True)


def _import_numerics(warm: bool = False) -> None:
    """Import :data:`PRELOAD`; ``warm``: with the warm-up (a worker), without it (the flow's
    own process, which only unpickles results)."""
    import importlib

    for name in PRELOAD:
        if name != "__main__" and (warm or name != WARM_UP):
            importlib.import_module(name)


def _warm_worker() -> int:
    """Run once on every Dask worker before the fit phase: import the numerics (what
    unpickling the first batch would otherwise do inside the fit phase) and one BLAS thread."""
    import os

    _import_numerics(warm=True)
    _init_worker()
    return os.getpid()


class DaskPool:
    """A Dask client used as the flow's pool: ``run`` sends one call to a worker and waits for
    its result. Thread-safe (the flow's task threads share it)."""

    def __init__(self, client: Any):
        self.client = client

    def run(self, fn: Callable[..., Any], *args: Any) -> Any:
        # pure=False: no hashing of the arguments to make a key, and no deduplication of two
        # identical calls (every batch is its own piece of work). The result comes back as one
        # pickled blob: left to Dask, every numpy buffer of the result's tables travels as a
        # frame of its own (961 frames for a 4-unit batch, 70 ms to serialise in the worker
        # against 24 ms for one pickle), each read separately by this process, which also runs
        # Prefect and the store (docs/benchmarks.md)
        import pickle

        blob = self.client.submit(_call_pickled, fn, *args, pure=False).result()
        return pickle.loads(blob)


def _call_pickled(fn: Callable[..., Any], *args: Any) -> bytes:
    import pickle

    return pickle.dumps(fn(*args), protocol=pickle.HIGHEST_PROTOCOL)


@contextmanager
def dask_pool(address: str | None = None, workers: int = 2) -> Iterator[DaskPool]:
    """A Dask cluster that :func:`run_in_pool` uses while the block runs: the scheduler at
    ``address``, else a ``LocalCluster`` of ``workers`` single-threaded worker processes
    (closed at the end). Every worker is warmed (:func:`_warm_worker`) before the block."""
    import logging as _logging

    import dask
    from distributed import Client, LocalCluster

    startup: dict[str, Any] = {"address": address, "cluster_start_s": 0.0}
    cluster = None
    t0 = time.perf_counter()
    if address is None:
        # the scheduler and the nannies run in this (the flow's) process and share its CPU
        # with Prefect and the store: their periodic callbacks run rarely. Idle, they cost
        # this process 0.04 CPU s per second with Dask's defaults, 0.009 with these: system
        # monitor (psutil, for a dashboard this cluster does not have) 0.5 -> 10 s, event-loop
        # health tick 20 -> 500 ms, nanny memory check 0.1 -> 1 s (still well before a
        # worker could fill this machine's memory)
        with dask.config.set(
            {
                "distributed.admin.system-monitor.interval": "10s",
                "distributed.admin.tick.interval": "500ms",
                "distributed.worker.memory.monitor-interval": "1s",
            }
        ):
            cluster = LocalCluster(
                n_workers=max(1, int(workers)),
                threads_per_worker=1,
                processes=True,
                dashboard_address=None,
                silence_logs=_logging.WARNING,
            )
        startup["cluster_start_s"] = time.perf_counter() - t0
    try:
        t1 = time.perf_counter()
        # results straight from the worker to this client: through the scheduler they would
        # be read and written once more (in this process, for a local cluster); workers at a
        # remote scheduler may not be reachable from here, so only for local ones
        client = Client(
            cluster if cluster is not None else address,
            set_as_default=False,
            direct_to_workers=_is_local_address(address),
        )
        startup["connect_s"] = time.perf_counter() - t1
        try:
            t2 = time.perf_counter()
            # the workers import in their processes while this one imports the same modules:
            # the flow needs them to unpickle the results (and its discovery check imports
            # scipy.stats), ~2 s of CPU that would otherwise be in the fit phase
            with ThreadPoolExecutor(1) as one:
                warming = one.submit(client.run, _warm_worker)
                _import_numerics()
                pids = warming.result()
            startup["warmup_s"] = time.perf_counter() - t2
            startup["workers"] = len(pids)
            startup["total_s"] = time.perf_counter() - t0
            last_dask_startup.clear()
            last_dask_startup.update(startup)
            _log.info(
                "Dask pool ready: %d workers, %.1f s (cluster %.1f s, warm-up %.1f s)",
                len(pids),
                startup["total_s"],
                startup["cluster_start_s"],
                startup["warmup_s"],
            )
            pool = DaskPool(client)
            with _active(pool):
                yield pool
        finally:
            client.close()
    finally:
        if cluster is not None:
            cluster.close()


def _is_local_address(address: str | None) -> bool:
    """Whether a scheduler address (None: a LocalCluster of ours) is on this machine."""
    import ipaddress
    from urllib.parse import urlparse

    if address is None:
        return True
    host = urlparse(address if "://" in address else "tcp://" + address).hostname
    if host in (None, "localhost"):
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


def active() -> bool:
    return _pool is not None


def dask_active() -> bool:
    """Whether the active pool is a Dask cluster (the ``dask`` runner opened it)."""
    return isinstance(_pool, DaskPool)


def run_in_pool(fn: Callable[..., Any], *args: Any) -> Any:
    """``fn(*args)`` in the current pool when a flow opened one, else in this process. ``fn``
    and its arguments must be picklable (module-level function, plain data)."""
    global _broken
    pool = _pool
    if pool is None or _broken:
        return fn(*args)
    if isinstance(pool, DaskPool):
        return _run_on_dask(pool, fn, *args)
    try:
        return pool.submit(fn, *args).result()
    except BrokenProcessPool as exc:
        with _lock:
            _broken = True
        _log.warning("compute pool broken (%s); running the remaining batches in the flow's process", exc)
        return fn(*args)


def _run_on_dask(pool: DaskPool, fn: Callable[..., Any], *args: Any) -> Any:
    global _broken
    from distributed import KilledWorker
    from distributed.comm.core import CommClosedError

    try:
        return pool.run(fn, *args)
    except KilledWorker as exc:
        # the scheduler already ran it again on other workers and each died: run it here once
        _log.warning("Dask workers died running a batch (%s); running it in the flow's process", exc)
        return fn(*args)
    except (CancelledError, CommClosedError) as exc:
        # the scheduler is gone (its futures are cancelled): the rest runs here
        with _lock:
            _broken = True
        _log.warning(
            "Dask cluster lost (%s: %s); running the remaining batches in the flow's process",
            type(exc).__name__,
            exc,
        )
        return fn(*args)
