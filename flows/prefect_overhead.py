"""Measure Prefect's overhead on this machine: temporary API start, per flow run, per task
with the thread pool, the process pool and prefect-dask. ``python -m flows.prefect_overhead``
prints a Markdown table (docs/flows.md records one run)."""
from __future__ import annotations

import os
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


def timed(fn, *a, **k) -> float:
    t = time.perf_counter()
    fn(*a, **k)
    return time.perf_counter() - t


def main() -> None:
    rows = []
    t_first = timed(empty_flow)
    rows.append(("first flow run (starts the temporary local API)", f"{t_first:.2f} s", "1"))
    with temporary_settings({PREFECT_FLOWS_HEARTBEAT_FREQUENCY: None}):
        n = 5
        t = sum(timed(empty_flow) for _ in range(n)) / n
        rows.append(("empty flow run, heartbeat off", f"{t * 1000:.0f} ms", str(n)))
    n = 3
    t_hb = sum(timed(empty_flow) for _ in range(n)) / n
    rows.append(("empty flow run, heartbeat on (Prefect default)", f"{t_hb * 1000:.0f} ms", str(n)))
    t = time.perf_counter()
    for i in range(10000):
        work(i)
    rows.append(("plain Python call (no Prefect)", f"{(time.perf_counter() - t) / 10000 * 1e6:.2f} us",
                 "10000"))
    with temporary_settings({PREFECT_FLOWS_HEARTBEAT_FREQUENCY: None}):
        base = sum(timed(empty_flow) for _ in range(3)) / 3
        for label, runner, n in (
            ("task, ThreadPoolTaskRunner(max_workers=2)", ThreadPoolTaskRunner(max_workers=2), 400),
            ("task, ProcessPoolTaskRunner(max_workers=2)", ProcessPoolTaskRunner(max_workers=2), 60),
        ):
            f = many_tasks.with_options(task_runner=runner)
            f(2)  # warm up (process pool: spawn)
            t = timed(f, n)
            rows.append((label, f"{(t - base) / n * 1000:.1f} ms", str(n)))
        try:
            from distributed import LocalCluster
            from prefect_dask import DaskTaskRunner
            with LocalCluster(n_workers=2, threads_per_worker=1, processes=False,
                              dashboard_address=None) as cluster:
                f = many_tasks.with_options(task_runner=DaskTaskRunner(address=cluster.scheduler_address))
                f(2)
                n = 100
                t = timed(f, n)
                rows.append(("task, prefect-dask on LocalCluster(2 workers, processes=False)",
                             f"{(t - base) / n * 1000:.1f} ms", str(n)))
        except ImportError as exc:
            rows.append(("prefect-dask", f"not installed ({exc})", "-"))
    load = os.getloadavg()[0]
    print(f"| what | cost | n |\n|---|---|---|")
    for r in rows:
        print(f"| {r[0]} | {r[1]} | {r[2]} |")
    print(f"\nload average during the run: {load:.1f} on {os.cpu_count()} cores")


if __name__ == "__main__":
    main()
