"""Measure Prefect's overhead on this machine: temporary API start, per flow run, and per
task run for each task runner of :mod:`flows.task_runners` (thread pool, process pool, Dask
LocalCluster of worker processes), with and without the shared API (a worker that reports to
the flow's server vs one that starts its own).

``python -m benchmarks.prefect_overhead [--quick]`` prints a Markdown table
(docs/flows.md records three runs). For each runner: the *fixed* cost of a flow run with
that runner (pool or cluster start, worker imports, each worker's first Prefect client) =
a 2-task flow minus an empty flow, the *per task* cost = the slope between the 2-task flow and
an N-task flow, CPU seconds of the whole process tree (this process, workers, API servers)
and how many Prefect API servers ran in the tree. The task does nothing (``x + 1``), so every
second measured is orchestration."""

from __future__ import annotations

import argparse
import os
import threading
import time

from flows import runtime

runtime.ensure_environment()

from prefect import flow, task  # noqa: E402
from prefect.cache_policies import NO_CACHE  # noqa: E402
from prefect.settings import PREFECT_FLOWS_HEARTBEAT_FREQUENCY, temporary_settings  # noqa: E402
from prefect.task_runners import ProcessPoolTaskRunner, ThreadPoolTaskRunner  # noqa: E402


def work(x: int) -> int:
    return x + 1


@task(persist_result=False, cache_policy=NO_CACHE)
def tiny(x: int) -> int:
    return work(x)


@flow(persist_result=False)
def empty_flow() -> int:
    return 0


@flow(persist_result=False)
def many_tasks(n: int) -> int:
    futs = [tiny.submit(i) for i in range(n)]
    return sum(f.result() for f in futs)


class TreeWatch:
    """CPU seconds of this process and every descendant (last value seen per pid, sampled every
    0.1 s, so a short-lived child is undercounted) and the Prefect API servers seen."""

    def __init__(self):
        self.cpu: dict[int, float] = {}
        self.servers: set[int] = set()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)

    def _sample(self) -> None:
        import psutil

        me = psutil.Process()
        try:
            procs = [me] + me.children(recursive=True)
        except psutil.Error:
            return
        for p in procs:
            try:
                t = p.cpu_times()
                self.cpu[p.pid] = t.user + t.system
                if p.pid != me.pid and "prefect.server" in " ".join(p.cmdline()):
                    self.servers.add(p.pid)
            except psutil.Error:
                pass

    def _run(self) -> None:
        while not self._stop.wait(0.1):
            self._sample()

    def __enter__(self):
        self._sample()
        self.cpu0 = dict(self.cpu)
        self._thread.start()
        return self

    def __exit__(self, *exc):
        self._stop.set()
        self._thread.join()
        self._sample()
        return False

    @property
    def cpu_s(self) -> float:
        return sum(v - self.cpu0.get(pid, 0.0) for pid, v in self.cpu.items())


def timed(fn, *a, **k) -> float:
    t = time.perf_counter()
    fn(*a, **k)
    return time.perf_counter() - t


def runners(quick: bool):
    from flows.task_runners import SharedApiProcessPoolTaskRunner, make_task_runner

    out = [
        ("thread pool (2)", lambda: ThreadPoolTaskRunner(max_workers=2), 400 if not quick else 100),
        (
            "process pool (2), shared API (mimucal)",
            lambda: SharedApiProcessPoolTaskRunner(2),
            60 if not quick else 20,
        ),
        (
            "process pool (2), Prefect default (own API per worker)",
            lambda: ProcessPoolTaskRunner(max_workers=2),
            60 if not quick else 20,
        ),
    ]
    try:
        from distributed import LocalCluster  # noqa: F401
        from prefect_dask import DaskTaskRunner

        def dask_plain():
            return DaskTaskRunner(
                cluster_class="distributed.LocalCluster",
                cluster_kwargs={
                    "n_workers": 2,
                    "threads_per_worker": 1,
                    "processes": True,
                    "dashboard_address": None,
                },
            )

        # mimucal's dask runner is a thread pool that hands batch numerics to the cluster:
        # a trivial task never reaches the cluster, so this row is the cluster's start cost
        out += [
            (
                "mimucal dask runner (thread pool + 2-worker LocalCluster, start included)",
                lambda: make_task_runner(kind="dask"),
                60 if not quick else 20,
            ),
            (
                "Dask LocalCluster (2 worker processes), prefect-dask default (own API per worker)",
                dask_plain,
                60 if not quick else 20,
            ),
        ]
    except ImportError:
        pass
    return out


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="fewer tasks (a few minutes)")
    ap.add_argument("--only", default="", help="substring of the runner names to measure")
    a = ap.parse_args(argv)
    import logging

    logging.getLogger("distributed").setLevel(logging.WARNING)
    rows = []
    t_first = timed(empty_flow)
    rows.append(("first flow run (starts the temporary local API)", f"{t_first:.2f} s", "", "", "1"))
    with temporary_settings({PREFECT_FLOWS_HEARTBEAT_FREQUENCY: None}):
        n = 5
        base = sum(timed(empty_flow) for _ in range(n)) / n
        rows.append(("empty flow run, heartbeat off", f"{base * 1000:.0f} ms", "", "", str(n)))
        for label, make, n in runners(a.quick):
            if a.only and a.only not in label:
                continue
            with TreeWatch() as w2:
                t2 = timed(many_tasks.with_options(task_runner=make()), 2)
            with TreeWatch() as wn:
                tn = timed(many_tasks.with_options(task_runner=make()), n)
            per_task = (tn - t2) / (n - 2)
            per_task_cpu = (wn.cpu_s - w2.cpu_s) / (n - 2)
            rows.append(
                (
                    label,
                    f"{(t2 - base):.2f} s (CPU {w2.cpu_s:.1f} s)",
                    f"{per_task * 1000:.1f} ms (CPU {per_task_cpu * 1000:.1f} ms)",
                    str(len(wn.servers)),
                    f"2, {n}",
                )
            )
            print(f"  {rows[-1]}", flush=True)
    load = os.getloadavg()
    print(
        "| runner | fixed cost per flow run, wall (tree CPU) | per task, wall (tree CPU) "
        "| API servers started in the tree | tasks |\n|---|---|---|---|---|"
    )
    for r in rows:
        print("| " + " | ".join(r) + " |")
    print(
        f"\nload average during the run: {load[0]:.1f} / {load[1]:.1f} / {load[2]:.1f} on "
        f"{os.cpu_count()} cores"
    )


if __name__ == "__main__":
    main()
