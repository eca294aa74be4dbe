"""flows.task_runners: the runner choice, and workers in other processes reporting to the
flow's own Prefect API server instead of starting one each (the cause of the slow Dask runs
in the first benchmark)."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

from flows import runtime

runtime.ensure_environment()

from prefect.task_runners import ThreadPoolTaskRunner  # noqa: E402

from flows import task_runners as tr  # noqa: E402

REPO = Path(__file__).resolve().parents[1]


def test_default_is_a_thread_pool_of_two(monkeypatch):
    monkeypatch.delenv(tr.RUNNER_ENV, raising=False)
    monkeypatch.delenv(tr.DASK_ENV, raising=False)
    r = tr.default_task_runner()
    assert type(r) is ThreadPoolTaskRunner
    assert r._max_workers == tr.LOCAL_WORKERS == 2


def test_runner_kind_from_argument_and_environment(monkeypatch):
    monkeypatch.delenv(tr.DASK_ENV, raising=False)
    p = tr.make_task_runner(kind="prefect-processes", max_workers=3)
    assert isinstance(p, tr.SharedApiProcessPoolTaskRunner)
    assert p._max_workers == 3 and p._initializer is tr.limit_worker_threads
    # the runner Prefect makes for each flow run keeps the class and the initializer
    d = p.duplicate()
    assert type(d) is tr.SharedApiProcessPoolTaskRunner and d._initializer is tr.limit_worker_threads
    monkeypatch.setenv(tr.RUNNER_ENV, "prefect-processes")
    assert isinstance(tr.make_task_runner(), tr.SharedApiProcessPoolTaskRunner)
    assert isinstance(tr.default_task_runner(), tr.SharedApiProcessPoolTaskRunner)
    monkeypatch.setenv(tr.RUNNER_ENV, "threads")
    assert type(tr.make_task_runner()) is ThreadPoolTaskRunner
    monkeypatch.setenv(tr.RUNNER_ENV, "fibres")
    with pytest.raises(ValueError, match="fibres"):
        tr.make_task_runner()


def test_dask_address_wins_and_the_dask_runner_keeps_its_cluster_settings(monkeypatch):
    monkeypatch.setenv(tr.RUNNER_ENV, "prefect-processes")
    r = tr.make_task_runner("tcp://127.0.0.1:8786")
    assert isinstance(r, tr.DaskPoolTaskRunner) and isinstance(r, ThreadPoolTaskRunner)
    assert r.address == "tcp://127.0.0.1:8786" and r._max_workers == tr.DASK_TASK_THREADS
    # the copy Prefect makes for each flow run keeps the class, the address and the sizes
    d = r.duplicate()
    assert type(d) is tr.DaskPoolTaskRunner and d == r and d.address == r.address
    monkeypatch.setenv(tr.DASK_ENV, "tcp://10.1.2.3:8786")
    assert tr.default_task_runner().address == "tcp://10.1.2.3:8786"
    local = tr.make_task_runner(kind="dask")
    assert local.address is None and local.n_workers == tr.LOCAL_WORKERS == 2
    assert local != r and tr.make_task_runner(kind="dask", max_workers=1).n_workers == 1
    # task threads: as given, and kept by the copy
    assert tr.DaskPoolTaskRunner(max_workers=3).duplicate()._max_workers == 3


def test_local_host_detection():
    import socket

    for h in ("127.0.0.1", "localhost", "::1", None, socket.gethostname()):
        assert tr._is_local_host(h), h
    for h in ("10.0.0.5", "192.168.1.20", "scheduler.example.org"):
        assert not tr._is_local_host(h), h


def test_shared_api_settings_leave_settings_alone_outside_a_flow_or_with_a_server():
    from prefect.settings import PREFECT_API_URL, temporary_settings

    before = PREFECT_API_URL.value()
    with tr.shared_api_settings():  # no flow run: nothing to share
        assert PREFECT_API_URL.value() == before
    with temporary_settings(updates={PREFECT_API_URL: "http://10.9.8.7:4200/api"}):
        with tr.shared_api_settings("tcp://127.0.0.1:8786"):
            assert PREFECT_API_URL.value() == "http://10.9.8.7:4200/api"


_SCRIPT = """
import json, os, sys
from flows import runtime
runtime.ensure_environment()
from prefect import flow, task
from prefect.cache_policies import NO_CACHE
from flows.task_runners import make_task_runner

@task(persist_result=False, cache_policy=NO_CACHE)
def where(i):
    from prefect.settings import PREFECT_API_URL
    from threadpoolctl import threadpool_info
    blas = [p["num_threads"] for p in threadpool_info() if p.get("user_api") == "blas"]
    return {"pid": os.getpid(), "api": PREFECT_API_URL.value(), "blas": blas}

@flow(persist_result=False)
def probe(n):
    from flows.task_runners import flow_api_url
    return {"flow_api": flow_api_url(), "flow_pid": os.getpid(),
            "tasks": [f.result() for f in [where.submit(i) for i in range(n)]]}

def main():
    import psutil
    result = {}
    for kind in sys.argv[1:]:  # one process: one temporary server for every runner
        out = probe.with_options(task_runner=make_task_runner(kind=kind, max_workers=1))(2)
        servers = [p for p in psutil.Process().children(recursive=True)
                   if "prefect.server" in " ".join(p.cmdline())]
        out["servers"] = len(servers)
        result[kind] = out
    print("RESULT " + json.dumps(result))

if __name__ == "__main__":
    main()
"""


@pytest.mark.slow
def test_workers_in_other_processes_use_the_flows_api_server(tmp_path):
    kinds = ["prefect-processes"]
    script = tmp_path / "probe_runner.py"
    script.write_text(textwrap.dedent(_SCRIPT))
    env = {k: v for k, v in os.environ.items() if k not in ("PREFECT_API_URL", "PREFECT_HOME")}
    env.update(
        PREFECT_HOME=str(tmp_path / "prefect-home"), PYTHONPATH=os.pathsep.join([str(REPO), str(tmp_path)])
    )
    p = subprocess.run(
        [sys.executable, str(script), *kinds],
        cwd=tmp_path,
        env=env,
        capture_output=True,
        text=True,
        timeout=900,
    )
    assert p.returncode == 0, p.stderr[-3000:]
    result = json.loads(next(ln for ln in p.stdout.splitlines() if ln.startswith("RESULT "))[7:])
    assert sorted(result) == sorted(kinds)
    for kind, out in result.items():
        assert out["flow_api"] and out["flow_api"].startswith("http://127.0.0.1:"), kind
        assert len(out["tasks"]) == 2
        for t in out["tasks"]:
            assert t["pid"] != out["flow_pid"], kind  # the task ran in a worker process
            assert t["api"].rstrip("/") == out["flow_api"], kind  # ... on the flow's server
            assert all(n == 1 for n in t["blas"]), kind  # one BLAS thread per worker
        # the flow's own temporary server and no other (Prefect's default: one per worker)
        assert out["servers"] == 1, kind


_DASK_SCRIPT = """
import json, os, sys

# only the standard library at the top: Dask's worker processes are spawned, and a spawned
# process runs the parent's main module again (as __mp_main__) before its first task


def numerics_where(i):
    from threadpoolctl import threadpool_info
    blas = [p["num_threads"] for p in threadpool_info() if p.get("user_api") == "blas"]
    return {"pid": os.getpid(), "prefect": "prefect" in sys.modules, "blas": blas,
            "warm": "calib_core.discovery" in sys.modules, "square": i * i}


def main():
    import psutil
    from flows import runtime
    runtime.ensure_environment()
    from prefect import flow, task
    from prefect.cache_policies import NO_CACHE
    from flows import compute_pool
    from flows.task_runners import make_task_runner, uses_unit_work_pool

    @task(persist_result=False, cache_policy=NO_CACHE)
    def batch(i):
        return {"task_pid": os.getpid(), **compute_pool.run_in_pool(numerics_where, i)}

    @flow(persist_result=False)
    def probe(n):
        from prefect.context import FlowRunContext
        return {"flow_pid": os.getpid(), "dask_active": compute_pool.dask_active(),
                "threads": FlowRunContext.get().task_runner._max_workers,
                "no_process_pool": not uses_unit_work_pool("auto", 1000),
                "startup": dict(compute_pool.last_dask_startup),
                "tasks": [f.result() for f in [batch.submit(i) for i in range(n)]]}

    out = probe.with_options(task_runner=make_task_runner(kind="dask", max_workers=2))(4)
    out["servers"] = len([p for p in psutil.Process().children(recursive=True)
                          if "prefect.server" in " ".join(p.cmdline())])
    out["children_after"] = len([p for p in psutil.Process().children(recursive=True)
                                 if not any(s in " ".join(p.cmdline()) for s in
                                            ("prefect.server", "resource_tracker"))])
    out["active_after"] = compute_pool.active()
    print("RESULT " + json.dumps(out))


if __name__ == "__main__":
    main()
"""


@pytest.mark.slow
def test_dask_runner_keeps_prefect_in_the_flow_and_the_numerics_on_warm_workers(tmp_path):
    script = tmp_path / "probe_dask.py"
    script.write_text(textwrap.dedent(_DASK_SCRIPT))
    env = {k: v for k, v in os.environ.items() if k not in ("PREFECT_API_URL", "PREFECT_HOME")}
    env.update(
        PREFECT_HOME=str(tmp_path / "prefect-home"), PYTHONPATH=os.pathsep.join([str(REPO), str(tmp_path)])
    )
    p = subprocess.run(
        [sys.executable, str(script)], cwd=tmp_path, env=env, capture_output=True, text=True, timeout=900
    )
    assert p.returncode == 0, p.stderr[-3000:]
    out = json.loads(next(ln for ln in p.stdout.splitlines() if ln.startswith("RESULT "))[7:])
    # the cluster was up and warm when the flow's body started, and the auto runner's
    # process pool is not opened on top of it
    assert out["dask_active"] and out["no_process_pool"]
    assert out["startup"]["workers"] == 2 and out["startup"]["cluster_start_s"] > 0
    assert out["threads"] == 4  # two task threads per Dask worker
    assert sorted(t["square"] for t in out["tasks"]) == [0, 1, 4, 9]
    for t in out["tasks"]:
        assert t["task_pid"] == out["flow_pid"]  # the Prefect task run: in the flow's process
        assert t["pid"] != out["flow_pid"]  # its numerics: on a Dask worker
        assert not t["prefect"] and t["warm"]  # no Prefect there; the numerics pre-imported
        assert all(n == 1 for n in t["blas"])  # one BLAS thread per worker
    assert out["servers"] == 1  # the flow's own temporary API server only
    # the flow's end closed the cluster (no worker process left) and the pool
    assert out["children_after"] == 0 and not out["active_after"]
