"""Which Prefect task runner a flow uses, and the settings its workers run with.

The nightly and rerun flows call :func:`default_task_runner` / :func:`make_task_runner`; the
choice of pool (and its size) lives here so that the flows stay orchestration only.

Runners (``MIMUCAL_TASK_RUNNER``, ``mimucal nightly --runner``, or the ``kind`` argument; Dask
at an address always wins):

- ``auto`` (default): ``processes`` when the run has at least :data:`AUTO_PROCESSES_MIN_UNITS`
  units to calibrate, else ``threads`` (the pool's start-up does not pay on a few units).
- ``threads``: a thread pool of :data:`LOCAL_WORKERS`. Cheapest per task, no
  start-up, but the unit work is Python and holds the GIL: the fit phase uses one core.
- ``processes``: the same thread pool of Prefect tasks, each handing its batch to a pool of
  :data:`LOCAL_WORKERS` worker processes forked from a forkserver that imported the numerics
  once (:mod:`flows.compute_pool`): both cores, no Prefect in the workers. The forkserver's
  imports (~1 s), the workers' forks and their warm-up run while Prefect starts
  (:func:`prestart_unit_work_pool`).
- ``prefect-processes``: Prefect's ``ProcessPoolTaskRunner`` (every task run in a spawned
  worker with its own Prefect client): both cores, but each worker pays its imports and
  Prefect's task context once (8-10 s CPU, docs/benchmarks.md).
- ``dask``: the same thread pool of Prefect tasks, each handing its batch to a Dask cluster
  (:class:`DaskPoolTaskRunner`): a ``LocalCluster`` of :data:`LOCAL_WORKERS` single-threaded
  worker processes started, and warmed, before the flow's body, or the scheduler at
  ``MIMUCAL_DASK_ADDRESS`` / ``--dask-address``. No Prefect in the workers.

Why the process-pool runner below is a subclass: a task that runs in another process builds
its own Prefect client from the settings shipped with the task. Without ``PREFECT_API_URL`` set,
that client starts *its own* temporary API server (a uvicorn
subprocess on the same SQLite database) in every worker: 15-30 s of start-up per worker on a
loaded machine, SQLite contention with the flow's server for every task-run state, and a
worker that hangs at shutdown. This was most of the 4.5x gap between Dask and the thread pool
in the first benchmark. The subclass puts the flow's own API URL into the settings a task
carries, so every worker talks to the one server the flow already runs. (The ``dask`` runner
used prefect-dask's ``DaskTaskRunner`` the same way until the third round; it now keeps the
task runs in the flow's process, docs/benchmarks.md.)
"""

from __future__ import annotations

import ipaddress
import os
import socket
from contextlib import nullcontext
from pathlib import Path
from typing import Any
from urllib.parse import urlparse

from prefect.task_runners import ProcessPoolTaskRunner, ThreadPoolTaskRunner

LOCAL_WORKERS = 2
DASK_ENV = "MIMUCAL_DASK_ADDRESS"  # the served deployment reads its Dask address here
DASK_WORKERS_ENV = "MIMUCAL_DASK_WORKERS"  # workers of the dask runner's LocalCluster (default 2)
RUNNER_ENV = "MIMUCAL_TASK_RUNNER"  # auto | threads | processes | prefect-processes | dask
RUNNER_KINDS = ("auto", "threads", "processes", "prefect-processes", "dask")
DEFAULT_KIND = "auto"
AUTO_PROCESSES_MIN_UNITS = 24  # three batches of 8: below that the pool's start-up dominates
# task threads of the dask runner: each waits on one batch at the cluster, so this bounds the
# batches the cluster works on at once (a remote cluster may have many workers)
DASK_TASK_THREADS = 16

# BLAS/OpenMP pools sized to one thread in worker processes: two workers on two cores must
# not each start a pool of two (Dask's nanny sets the same for its workers).
_ONE_THREAD_ENV = {"OMP_NUM_THREADS": "1", "OPENBLAS_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}


def _is_local_host(host: str | None) -> bool:
    if not host:
        return True
    if host in ("localhost", socket.gethostname()):
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


def flow_api_url() -> str | None:
    """The API URL the current flow run's client talks to (its temporary local server, or a
    real server), or None outside a flow run."""
    from prefect.context import FlowRunContext, TaskRunContext

    ctx = FlowRunContext.get() or TaskRunContext.get()
    url = getattr(getattr(ctx, "client", None), "api_url", None)
    return str(url).rstrip("/") if url else None


def shared_api_settings(worker_address: str | None = None):
    """A context in which the settings serialised for a task name the flow's API URL, so that
    a task run in another process reports to the flow's server instead of starting its own.

    Nothing changes when ``PREFECT_API_URL`` is already set (a real server: it travels with
    the settings anyway), outside a flow run, or when the flow's server is a loopback one and
    the workers are on another machine (``worker_address`` not local: they could not reach
    it; such a deployment needs a real server, see docs/flows.md)."""
    from prefect.settings import PREFECT_API_URL, temporary_settings

    if PREFECT_API_URL.value():
        return nullcontext()
    url = flow_api_url()
    if not url:
        return nullcontext()
    if (
        worker_address is not None
        and not _is_local_host(urlparse(worker_address).hostname)
        and _is_local_host(urlparse(url).hostname)
    ):
        return nullcontext()
    return temporary_settings(updates={PREFECT_API_URL: url})


def limit_worker_threads() -> None:
    """Process-pool worker initializer: one BLAS/OpenMP thread per worker process (set before
    numpy is imported, and applied to any pool already loaded)."""
    for k, v in _ONE_THREAD_ENV.items():
        os.environ[k] = v
    try:
        from threadpoolctl import threadpool_limits

        threadpool_limits(limits=1)
    except Exception:  # threadpoolctl missing or no pool loaded yet: the env vars do it
        pass


class SharedApiProcessPoolTaskRunner(ProcessPoolTaskRunner):
    """Prefect's process pool whose workers report to the flow's API server (see module doc)
    and run one BLAS thread each."""

    def __init__(self, max_workers: int | None = None, **kwargs: Any):
        kwargs.setdefault("initializer", limit_worker_threads)
        super().__init__(max_workers=max_workers, **kwargs)

    def submit(self, task, parameters, wait_for=None, dependencies=None):
        with shared_api_settings():
            return super().submit(task, parameters, wait_for=wait_for, dependencies=dependencies)


class DaskPoolTaskRunner(ThreadPoolTaskRunner):
    """The ``dask`` runner: Prefect tasks in the flow's thread pool (as ``processes``), each
    handing its batch's numerics to a Dask cluster through :func:`flows.compute_pool.dask_pool`
    (``address``: a running scheduler; else a ``LocalCluster`` of ``n_workers`` started here).

    The cluster is opened, and its workers warmed (numerics imported), when Prefect enters the
    runner at the start of the flow run, before the flow's body: the fit phase no longer pays
    a worker's imports nor Prefect's task context in the worker (8-10 s CPU per worker before,
    docs/benchmarks.md). Task-run states stay in the flow's process; the workers never talk to
    Prefect's API. Task threads (each waits on one batch; no CPU while it waits): ``max_workers``
    when given, else two per Dask worker found at the start (at most :data:`DASK_TASK_THREADS`),
    enough to keep every worker fed; each thread builds its own Prefect client on its first task
    (~20-40 ms of CPU, mostly an SSL context), so idle extra threads are not free."""

    def __init__(
        self, address: str | None = None, n_workers: int = LOCAL_WORKERS, max_workers: int | None = None
    ):
        super().__init__(max_workers=max_workers or DASK_TASK_THREADS)
        self.address = address
        self.n_workers = n_workers
        self._threads_given = max_workers
        self._dask_pool = None

    def duplicate(self):
        return type(self)(address=self.address, n_workers=self.n_workers, max_workers=self._threads_given)

    def __eq__(self, value: object) -> bool:
        return (
            isinstance(value, DaskPoolTaskRunner)
            and value.address == self.address
            and value.n_workers == self.n_workers
            and value._threads_given == self._threads_given
        )

    def __enter__(self):
        from flows.compute_pool import dask_pool, last_dask_startup

        pool = dask_pool(self.address, self.n_workers)
        pool.__enter__()  # may raise (no scheduler at the address): nothing to undo then
        self._dask_pool = pool
        if not self._threads_given:
            workers = int(last_dask_startup.get("workers") or self.n_workers)
            self._max_workers = min(DASK_TASK_THREADS, max(2, 2 * workers))
        try:
            return super().__enter__()
        except BaseException:
            self._dask_pool, pool = None, self._dask_pool
            pool.__exit__(None, None, None)
            raise

    def __exit__(self, exc_type: Any, exc_value: Any, traceback: Any) -> None:
        try:
            super().__exit__(exc_type, exc_value, traceback)
        finally:
            pool, self._dask_pool = self._dask_pool, None
            if pool is not None:
                pool.__exit__(None, None, None)


def resolve_kind(kind: str | None = None) -> str:
    """``kind``, else ``$MIMUCAL_TASK_RUNNER``, else ``auto``; checked against RUNNER_KINDS."""
    kind = (kind or os.environ.get(RUNNER_ENV) or DEFAULT_KIND).strip().lower()
    if kind not in RUNNER_KINDS:
        raise ValueError(
            f"unknown task runner {kind!r} (${RUNNER_ENV}): choose one of " + ", ".join(RUNNER_KINDS)
        )
    return kind


def make_task_runner(
    dask_address: str | None = None, max_workers: int = LOCAL_WORKERS, kind: str | None = None
):
    """The Prefect task runner for a flow: Dask at ``dask_address`` when given, else ``kind``
    (see module doc) with ``max_workers`` workers. ``auto`` and ``processes`` run their
    Prefect tasks in a thread pool; :func:`unit_work_pool` adds the worker processes."""
    if dask_address:
        return DaskPoolTaskRunner(address=dask_address)
    kind = resolve_kind(kind)
    if kind in ("auto", "threads", "processes"):
        return ThreadPoolTaskRunner(max_workers=max_workers)
    if kind == "prefect-processes":
        return SharedApiProcessPoolTaskRunner(max_workers=max_workers)
    return DaskPoolTaskRunner(n_workers=int(os.environ.get(DASK_WORKERS_ENV) or max_workers))


def uses_unit_work_pool(kind: str | None, n_units: int) -> bool:
    """Whether a run of ``n_units`` units with runner ``kind`` hands its batches to
    :mod:`flows.compute_pool` worker processes."""
    from flows.compute_pool import dask_active

    if dask_active():  # the flow's task runner already sends the work to a Dask cluster
        return False
    kind = resolve_kind(kind)
    return kind == "processes" or (kind == "auto" and n_units >= AUTO_PROCESSES_MIN_UNITS)


def unit_work_pool(kind: str | None, n_units: int, workers: int = LOCAL_WORKERS):
    """The context in which a flow runs its batches: a :func:`flows.compute_pool.compute_pool`
    of ``workers`` processes when :func:`uses_unit_work_pool`, else nothing."""
    if workers > 1 and uses_unit_work_pool(kind, n_units):
        from flows.compute_pool import compute_pool

        return compute_pool(workers)
    return nullcontext()


def prestart_unit_work_pool(kind: str | None, dataset: str | Path) -> bool:
    """Before a flow run: when a run over the fleet at ``dataset`` may hand its batches to
    worker processes (:func:`unit_work_pool`, judged by the unit directories there, an upper
    bound of the units to calibrate), start their forkserver and the workers now, so that the
    imports, the forks and the workers' warm-up overlap Prefect's start-up
    (:func:`flows.compute_pool.prestart_workers`; a run that does not use them shuts them
    down). Returns whether they were started."""
    from schemas.dataset import count_unit_dirs

    if LOCAL_WORKERS < 2 or not uses_unit_work_pool(kind, count_unit_dirs(dataset)):
        return False
    from flows.compute_pool import prestart_workers, start_forkserver

    start_forkserver()
    prestart_workers(LOCAL_WORKERS)
    return True


def default_task_runner():
    """The runner a flow gets when its caller does not choose: Dask at ``$MIMUCAL_DASK_ADDRESS``
    when set, else :func:`make_task_runner`'s default."""
    return make_task_runner(os.environ.get(DASK_ENV) or None)
