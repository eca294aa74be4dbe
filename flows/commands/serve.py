"""``mimucal serve DATASET --results DIR``: register the nightly deployment with a cron
schedule and serve it (runs until interrupted).

Prefect does not schedule on its temporary local API, so ``serve`` needs a real server: the
one in ``PREFECT_API_URL`` (or ``--api-url``) when set, otherwise it starts
``prefect server start --host 127.0.0.1 --port PORT`` itself with its SQLite database and log
in ``RESULTS/.prefect-server/`` and stops it on exit. Stopping ``serve`` pauses the
deployment's schedule (Prefect's default)."""

from __future__ import annotations

import argparse
import os
import signal
import subprocess
import sys
import time
import urllib.request
from pathlib import Path

from flows.cli import CliError

EPILOG = """examples:
  mimucal serve data/fleet --results results                      # 02:00 UTC every night
  mimucal serve data/fleet --results results --cron "30 1 * * 1-5" --timezone Europe/Paris
  PREFECT_API_URL=http://prefect.lab:4200/api mimucal serve data/fleet --results results

Trigger a run by hand:  prefect deployment run nightly-fleet-calibration/mimucal-nightly"""


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "serve",
        help="serve the nightly flow on a cron schedule (Prefect server)",
        description=__doc__,
        epilog=EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("dataset", metavar="DATASET", help="hive dataset root")
    p.add_argument("--results", required=True, metavar="DIR", help="results store directory")
    p.add_argument("--cron", default="0 2 * * *", help='cron schedule (default "0 2 * * *")')
    p.add_argument("--timezone", default="UTC", help="IANA time zone of the schedule (default UTC)")
    p.add_argument("--name", default="mimucal-nightly", help="deployment name")
    p.add_argument("--config", metavar="TOML", default=None, help="outlier options and limits")
    p.add_argument(
        "--dask-address", metavar="ADDR", default=None, help="run the per-unit tasks on this Dask scheduler"
    )
    p.add_argument(
        "--api-url", default=None, help="Prefect server API (default PREFECT_API_URL, else start one)"
    )
    p.add_argument("--port", type=int, default=4200, help="port of the server started here")
    p.set_defaults(func=run)


def _healthy(api_url: str) -> bool:
    try:
        with urllib.request.urlopen(api_url.rstrip("/") + "/health", timeout=2) as r:
            return r.status == 200
    except Exception:
        return False


def start_server(results: Path, port: int, timeout_s: float = 120.0) -> tuple[subprocess.Popen, str]:
    """``prefect server start`` on 127.0.0.1:port with SQLite under RESULTS/.prefect-server."""
    home = (results / ".prefect-server").resolve()
    home.mkdir(parents=True, exist_ok=True)
    env = dict(os.environ)
    env.update(
        {
            "PREFECT_HOME": str(home),
            "PREFECT_SERVER_DATABASE_CONNECTION_URL": f"sqlite+aiosqlite:///{home / 'prefect.db'}",
            "PREFECT_SERVER_ANALYTICS_ENABLED": "false",
            "DO_NOT_TRACK": "1",
            "PREFECT_UI_ENABLED": "false",
            "PREFECT_LOGGING_LEVEL": "WARNING",
        }
    )
    env.pop("PREFECT_API_URL", None)
    exe = Path(sys.executable).parent / "prefect"
    cmd = [
        str(exe) if exe.exists() else "prefect",
        "server",
        "start",
        "--host",
        "127.0.0.1",
        "--port",
        str(port),
    ]
    log = open(home / "server.log", "ab")
    proc = subprocess.Popen(cmd, env=env, stdout=log, stderr=subprocess.STDOUT, start_new_session=True)
    api_url = f"http://127.0.0.1:{port}/api"
    t0 = time.monotonic()
    while time.monotonic() - t0 < timeout_s:
        if proc.poll() is not None:
            raise CliError(f"prefect server exited with code {proc.returncode}; see {home / 'server.log'}")
        if _healthy(api_url):
            return proc, api_url
        time.sleep(0.5)
    stop_server(proc)
    raise CliError(
        f"prefect server on port {port} not healthy after {timeout_s:.0f} s; see {home / 'server.log'}"
    )


def stop_server(proc: subprocess.Popen) -> None:
    if proc.poll() is None:
        proc.terminate()
        try:
            proc.wait(timeout=15)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()


def run(args: argparse.Namespace) -> int:
    dataset = Path(args.dataset).resolve()
    results = Path(args.results).resolve()
    if not dataset.is_dir():
        raise CliError(f"dataset {dataset} is not a directory")
    try:
        from zoneinfo import ZoneInfo

        ZoneInfo(args.timezone)
    except Exception:
        raise CliError(f"--timezone {args.timezone!r} is not an IANA time zone") from None
    from flows import runtime

    runtime.ensure_environment(results)
    api_url = args.api_url or os.environ.get("PREFECT_API_URL")
    server = None
    if not api_url:
        server, api_url = start_server(results, args.port)
        print(
            f"started prefect server at {api_url} (pid {server.pid}); log "
            f"{results / '.prefect-server' / 'server.log'}",
            flush=True,
        )
    elif not _healthy(api_url):
        raise CliError(f"no healthy Prefect server at {api_url}")
    os.environ["PREFECT_API_URL"] = api_url  # the runs' subprocesses inherit it
    if args.dask_address:
        os.environ["MIMUCAL_DASK_ADDRESS"] = args.dask_address

    def _term(signum, frame):
        raise KeyboardInterrupt

    signal.signal(signal.SIGTERM, _term)
    try:
        from prefect.schedules import Cron
        from prefect.settings import PREFECT_API_URL, temporary_settings

        from flows.nightly import nightly_flow

        params = {"dataset": str(dataset), "results": str(results), "progress": False}
        if args.config:
            params["config"] = str(Path(args.config).resolve())
        with temporary_settings(updates={PREFECT_API_URL: api_url}):
            print(
                f"serving deployment nightly-fleet-calibration/{args.name}: cron "
                f"{args.cron!r} ({args.timezone}), dataset {dataset}, results {results}",
                flush=True,
            )
            nightly_flow.serve(
                name=args.name,
                schedules=[Cron(args.cron, timezone=args.timezone)],
                parameters=params,
                print_starting_message=False,
            )
    except KeyboardInterrupt:
        pass
    finally:
        if server is not None:
            stop_server(server)
    return 0
