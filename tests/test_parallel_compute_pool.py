"""flows.compute_pool: the unit work in forkserver worker processes, and what happens when a
worker dies."""
from __future__ import annotations

import os
import signal

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
