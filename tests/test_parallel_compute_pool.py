"""flows.compute_pool: the unit work in forkserver worker processes or on a Dask cluster, and
what happens when a worker dies."""

from __future__ import annotations

import os
import signal

import pytest

from flows import compute_pool as cp


def _pid_and_square(x: int) -> tuple[int, int]:
    return os.getpid(), x * x


def _die_once(marker: str) -> int:
    # the first call kills its own worker (as the OOM killer would); a later call, in the
    # flow's process, finds the marker and returns normally
    if not os.path.exists(marker):
        open(marker, "w").close()
        os.kill(os.getpid(), signal.SIGKILL)
    return os.getpid()


def test_without_a_pool_the_work_runs_here():
    assert not cp.active()
    assert cp.run_in_pool(_pid_and_square, 3) == (os.getpid(), 9)


@pytest.mark.slow
def test_work_runs_in_worker_processes_and_the_pool_is_closed_after():
    with cp.compute_pool(2):
        assert cp.active()
        out = [cp.run_in_pool(_pid_and_square, i) for i in range(6)]
    assert [sq for _, sq in out] == [i * i for i in range(6)]
    assert all(pid != os.getpid() for pid, _ in out)
    assert not cp.active()


def test_a_dead_worker_costs_time_not_the_batch(tmp_path):
    marker = str(tmp_path / "died")
    with cp.compute_pool(2):
        pid = cp.run_in_pool(_die_once, marker)  # the worker dies; rerun in this process
        assert pid == os.getpid() and os.path.exists(marker)
        # the pool is broken: later batches run here too, none is lost
        assert cp.run_in_pool(_pid_and_square, 4) == (os.getpid(), 16)
    assert not cp.active()


# --- the Dask backend (the ``dask`` runner) ------------------------------------------------------
def _where_and_what(x: int) -> dict:
    import sys

    return {
        "pid": os.getpid(),
        "square": x * x,
        "prefect": "prefect" in sys.modules,
        "numerics": "calib_core.discovery" in sys.modules,
    }


def _die_unless(flow_pid: int, marker: str | None = None) -> int:
    # kills the Dask worker that runs it (as the OOM killer would): always, or only the first
    # time when a marker file is given; returns normally in the flow's process
    if os.getpid() != flow_pid and (marker is None or not os.path.exists(marker)):
        if marker is not None:
            open(marker, "w").close()
        os.kill(os.getpid(), signal.SIGKILL)
    return os.getpid()


def _one_worker_cluster():
    """A scheduler with one worker, standing for a cluster at an address (``--dask-address``);
    a task that kills two workers fails (``KilledWorker``)."""
    import logging

    import dask
    from distributed import LocalCluster

    with dask.config.set({"distributed.scheduler.allowed-failures": 1}):
        return LocalCluster(
            n_workers=1,
            threads_per_worker=1,
            processes=True,
            dashboard_address=None,
            silence_logs=logging.ERROR,
        )


@pytest.fixture(scope="module")
def cluster():
    c = _one_worker_cluster()
    yield c
    c.close()


@pytest.fixture
def own_cluster():
    c = _one_worker_cluster()
    yield c
    c.close()


@pytest.mark.slow
def test_a_batch_that_kills_every_worker_runs_in_the_flows_process(own_cluster):
    # allowed-failures 1: the scheduler tries the batch twice, then gives up (KilledWorker);
    # the batch then runs here, and the pool keeps working
    with cp.dask_pool(own_cluster.scheduler_address):
        assert cp.run_in_pool(_die_unless, os.getpid()) == os.getpid()
        assert cp.run_in_pool(_where_and_what, 2)["pid"] != os.getpid()


@pytest.mark.slow
def test_dask_workers_are_warmed_before_the_first_batch_and_run_no_prefect(cluster):
    with cp.dask_pool(cluster.scheduler_address):
        assert cp.active() and cp.dask_active()
        start = dict(cp.last_dask_startup)
        out = [cp.run_in_pool(_where_and_what, i) for i in range(3)]
    assert [o["square"] for o in out] == [0, 1, 4]
    assert all(o["pid"] != os.getpid() for o in out)  # ran on the worker
    assert not any(o["prefect"] for o in out)  # the worker never imported Prefect
    assert all(o["numerics"] for o in out)  # imported by the warm-up, before the batch
    assert start["workers"] == 1 and start["warmup_s"] > 0 and start["cluster_start_s"] == 0
    assert not cp.active() and not cp.dask_active()
    # a cluster at an address is not ours to close: still there after the pool
    assert len(cluster.scheduler_info["workers"]) == 1


@pytest.mark.slow
def test_a_dead_dask_worker_costs_time_not_the_batch(cluster, tmp_path):
    marker = str(tmp_path / "died")
    with cp.dask_pool(cluster.scheduler_address):
        pid = cp.run_in_pool(_die_unless, os.getpid(), marker)
        # the worker died once; its nanny started a new one and the scheduler ran the batch
        # again there (not in this process)
        assert os.path.exists(marker) and pid != os.getpid()
        assert cp.run_in_pool(_where_and_what, 5)["square"] == 25


# --- the forkserver started before the flow, and the workers' reads -----------------------------
def _arrow_threads_here() -> bool:
    from schemas import reader

    return reader._arrow_threads


def test_workers_read_on_their_own_thread_and_this_process_keeps_arrows_threads():
    from schemas import reader

    # the precondition set here: an earlier test in this process (a Dask cluster whose
    # workers are threads of this process) may have switched them off
    reader.use_arrow_threads(True)
    with cp.compute_pool(2):
        assert cp.run_in_pool(_arrow_threads_here) is False
    assert reader._arrow_threads is True


def test_a_pool_forks_its_workers_from_the_forkserver_started_before_it():
    from multiprocessing import forkserver

    cp.start_forkserver()
    server = forkserver._forkserver._forkserver_pid  # the stdlib keeps it private
    assert server is not None and server != os.getpid()
    cp.start_forkserver()  # a second call starts nothing new
    assert forkserver._forkserver._forkserver_pid == server
    with cp.compute_pool(2):
        parents = {cp.run_in_pool(os.getppid) for _ in range(4)}
    assert parents == {server}


def _fleet_dirs(root, units_per_lot: dict[str, int]):
    for lot, n in units_per_lot.items():
        for i in range(n):
            (root / f"lot={lot}" / f"unit=U{i:03d}" / "rep=1").mkdir(parents=True)
    (root / "notes").mkdir()  # not a lot: not counted
    (root / "lot=L1" / ".hidden").mkdir()  # hidden: not counted
    return root


def test_count_unit_dirs(tmp_path):
    from schemas.dataset import count_unit_dirs

    assert count_unit_dirs(_fleet_dirs(tmp_path, {"L1": 3, "L2": 4})) == 7
    assert count_unit_dirs(tmp_path / "missing") == 0


def test_the_forkserver_is_started_early_only_when_the_run_may_use_worker_processes(tmp_path, monkeypatch):
    from flows.task_runners import AUTO_PROCESSES_MIN_UNITS, LOCAL_WORKERS, prestart_unit_work_pool

    started: list[int] = []
    monkeypatch.setattr(cp, "start_forkserver", lambda: started.append(1))
    monkeypatch.setattr(cp, "prestart_workers", lambda workers: started.append(workers) or True)
    few = _fleet_dirs(tmp_path / "few", {"L1": AUTO_PROCESSES_MIN_UNITS - 1})
    many = _fleet_dirs(tmp_path / "many", {"L1": AUTO_PROCESSES_MIN_UNITS - 1, "L2": 1})
    assert not prestart_unit_work_pool("threads", many)
    assert not prestart_unit_work_pool("auto", few)  # auto stays on threads below the minimum
    assert not started
    assert prestart_unit_work_pool("auto", many)
    assert prestart_unit_work_pool("processes", few)
    assert started == [1, LOCAL_WORKERS] * 2  # the forkserver, then the workers


def test_the_nightly_launcher_starts_the_forkserver_before_prefect(tmp_path, monkeypatch):
    from flows import nightly

    order: list[str] = []
    monkeypatch.setattr(
        nightly, "prestart_unit_work_pool", lambda kind, dataset: order.append(f"prestart {kind}")
    )

    class _Flow:  # stands for the Prefect flow: records that it ran, and after what
        def with_options(self, **_):
            return lambda *a, **k: order.append(f"flow {k['runner']}") or {}

    monkeypatch.setattr(nightly, "nightly_flow", _Flow())
    nightly.nightly_fleet_calibration(tmp_path / "d", tmp_path / "r", runner="processes")
    nightly.nightly_fleet_calibration(tmp_path / "d", tmp_path / "r", runner="threads")
    # a Dask cluster's workers are warmed by its task runner: no forkserver for them
    nightly.nightly_fleet_calibration(tmp_path / "d", tmp_path / "r", dask_address="tcp://127.0.0.1:1")
    assert order == ["prestart processes", "flow processes", "prestart threads", "flow threads", "flow dask"]


def _warm_up_here() -> tuple[float | None, str | None, int]:
    from flows import worker_warmup

    return worker_warmup.warm_up_s, worker_warmup.warm_up_error, os.getpid()


def test_workers_are_forked_with_the_unit_pipeline_already_run_once():
    # the forkserver imports flows.worker_warmup last, which calibrates a simulated unit
    # (discovery and noise included): every worker inherits its first-call costs paid
    assert cp.PRELOAD[-1] == cp.WARM_UP
    with cp.compute_pool(2):
        seen = [cp.run_in_pool(_warm_up_here) for _ in range(2)]
    for took, error, pid in seen:
        assert pid != os.getpid()
        assert error is None
        assert took is not None and took > 0


def test_waiting_for_the_forkserver_leaves_it_ready_for_the_pool():
    from multiprocessing import forkserver

    cp.wait_for_forkserver()  # returns once a child could be forked from it (imports done)
    server = forkserver._forkserver._forkserver_pid  # the stdlib keeps it private
    assert server is not None and server != os.getpid()
    with cp.compute_pool(2):
        assert cp.run_in_pool(os.getppid) == server


def _forked_warm_up_here() -> tuple[float | None, int]:
    from flows import worker_warmup

    return worker_warmup.forked_warm_up_s, os.getpid()


def _worker_processes(pool) -> list:
    return list(pool._processes.values())  # the stdlib keeps them private


def test_prestarted_workers_are_warmed_after_their_fork_and_adopted_by_the_pool():
    assert cp.prestart_workers(2)
    assert not cp.prestart_workers(2)  # some are waiting already: nothing more started
    assert cp.wait_for_prestarted_workers()
    started = {p.pid for p in _worker_processes(cp._prestarted[0])}
    assert len(started) == 2
    with cp.compute_pool(2):
        seen = [cp.run_in_pool(_forked_warm_up_here) for _ in range(6)]
    assert {pid for _, pid in seen} <= started  # the same processes, no new fork
    # each ran the unit pipeline once more before its first call (worker_warmup)
    assert all(took is not None and took > 0 for took, _ in seen)
    assert cp._prestarted is None and not cp.wait_for_prestarted_workers()
    with cp.compute_pool(1):  # a pool opened without prestarted workers: forked cold
        took, pid = cp.run_in_pool(_forked_warm_up_here)
    assert took is None and pid not in started


def test_prestarted_workers_of_another_size_or_not_adopted_are_shut_down():
    cp.prestart_workers(1)
    cp.wait_for_prestarted_workers()
    (first,) = _worker_processes(cp._prestarted[0])
    with cp.compute_pool(2):  # not the prestarted size: new workers
        pids = {cp.run_in_pool(os.getpid) for _ in range(4)}
    assert first.pid not in pids
    first.join(timeout=10)
    assert not first.is_alive()
    cp.prestart_workers(1)
    cp.wait_for_prestarted_workers()
    (second,) = _worker_processes(cp._prestarted[0])
    cp.discard_prestarted_workers()
    second.join(timeout=10)
    assert not second.is_alive() and cp._prestarted is None


def test_the_nightly_shuts_down_workers_it_started_and_did_not_use(tmp_path, monkeypatch):
    from flows import nightly

    monkeypatch.setattr(nightly, "prestart_unit_work_pool", lambda kind, dataset: cp.prestart_workers(1))
    workers: list = []

    class _Flow:  # stands for a Prefect flow that ends before its fit phase
        def with_options(self, **_):
            def run(*a, **k):
                workers.extend(_worker_processes(cp._prestarted[0]))
                raise RuntimeError("the flow failed before its fit phase")

            return run

    monkeypatch.setattr(nightly, "nightly_flow", _Flow())
    with pytest.raises(RuntimeError):
        nightly.nightly_fleet_calibration(tmp_path / "d", tmp_path / "r", runner="processes")
    assert cp._prestarted is None and workers
    for w in workers:
        w.join(timeout=10)
        assert not w.is_alive()


def test_workers_that_cannot_be_started_ahead_leave_the_run_to_start_its_own(monkeypatch, caplog):
    def no_fork(self, fn, *args):
        raise OSError("Resource temporarily unavailable")

    monkeypatch.setattr(cp.ProcessPoolExecutor, "submit", no_fork)
    with caplog.at_level("WARNING", logger=cp.__name__):
        assert not cp.prestart_workers(2)
    assert cp._prestarted is None
    assert "not started ahead (Resource temporarily unavailable)" in caplog.text
    monkeypatch.undo()
    with cp.compute_pool(2):  # the fit phase's own pool
        assert cp.run_in_pool(os.getpid) != os.getpid()
