"""``mimucal serve`` against a real Prefect server: the deployment is registered with its cron
schedule and time zone, and a triggered run completes and writes the store."""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import pytest

from flows import runtime

runtime.ensure_environment()

from schemas.results_store import ResultsStore  # noqa: E402

pytestmark = [pytest.mark.server, pytest.mark.slow]

DEPLOYMENT = "nightly-fleet-calibration/mimucal-nightly"


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_serve_registers_cron_deployment_and_a_triggered_run_completes(tmp_path):
    from prefect.client.orchestration import get_client
    from prefect.deployments import run_deployment
    from prefect.settings import PREFECT_API_URL, temporary_settings

    from flows.fleet_sim import simulate_fleet

    data, results = tmp_path / "data", tmp_path / "results"
    simulate_fleet(data, lots=1, units=2, reps=2, seed=5, sample_rate_hz=20.0)
    port = free_port()
    api = f"http://127.0.0.1:{port}/api"
    env = {k: v for k, v in os.environ.items() if k not in ("PREFECT_API_URL", "PREFECT_HOME")}
    exe = Path(sys.executable).parent / "mimucal"
    cmd = [
        str(exe),
        "serve",
        str(data),
        "--results",
        str(results),
        "--port",
        str(port),
        "--cron",
        "15 3 * * *",
        "--timezone",
        "Europe/Paris",
    ]
    proc = subprocess.Popen(
        cmd, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, start_new_session=True
    )
    try:
        with temporary_settings(updates={PREFECT_API_URL: api}):
            import asyncio

            async def deployment():
                async with get_client() as client:
                    return await client.read_deployment_by_name(DEPLOYMENT)

            dep, t0 = None, time.monotonic()
            while time.monotonic() - t0 < 240 and proc.poll() is None:
                try:
                    dep = asyncio.run(deployment())
                    break
                except Exception:
                    time.sleep(1.0)
            assert dep is not None, f"no deployment; serve exited {proc.poll()}"
            crons = [(s.schedule.cron, s.schedule.timezone, s.active) for s in dep.schedules]
            assert crons == [("15 3 * * *", "Europe/Paris", True)]
            assert dep.parameters["results"] == str(results.resolve())
            run = run_deployment(DEPLOYMENT, timeout=240)
            assert run.state.is_completed(), run.state
        assert ResultsStore(results).exists()
        assert list((results / "tables" / "sessions").glob("lot=*.parquet"))
        assert (results / "runs").glob("*.json")
    finally:
        os.killpg(proc.pid, signal.SIGTERM)
        try:
            proc.wait(timeout=30)
        except subprocess.TimeoutExpired:
            os.killpg(proc.pid, signal.SIGKILL)
    # the server started by serve was stopped with it
    time.sleep(1.0)
    with socket.socket() as s:
        assert s.connect_ex(("127.0.0.1", port)) != 0
