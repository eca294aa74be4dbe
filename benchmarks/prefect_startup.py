"""What Prefect's temporary API server costs a command, and which settings cut it.

``python -m benchmarks.prefect_startup [--repeats N]`` runs each case in a fresh process
(as a ``mimucal`` command starts) and prints a Markdown table: the seconds to ``import
prefect``, the first (empty) flow run (the temporary server's start: uvicorn, the SQLite
database created or checked and migrated, the flow run's records), and a second empty flow
run in the same process (the per-run cost once the server is up). Cases:

- ``new home``: an empty ``PREFECT_HOME`` (a new ``--results`` directory: mimucal keeps the
  home in ``<results>/.prefect``), the database created and migrated at start;
- ``existing home``: the same home a second time (the database is there; migrations are
  checked);
- ``new home, template db``: an empty home into which a migrated ``prefect.db`` of the same
  Prefect version is copied first (what a cached template saves);
- ``existing home, no migrate check``: ``PREFECT_SERVER_DATABASE_MIGRATE_ON_START=false``
  (safe only on a database this Prefect version migrated).

``--nightly N`` measures instead what a whole ``mimucal nightly`` of one simulated N-unit lot
costs outside its flow: the command's wall time minus the flow body (the run log's
``elapsed_s``), split into the time before the flow body (interpreter, imports, the API
server's start, the flow run's creation: the run log's ``start`` minus the launch) and after
it (the run's end, the server's stop, the process's exit), with the CPU time of the command's
process tree (the API server and the worker processes included); on a new results directory
(a new home) and again with ``--force`` on the same one (an existing home), with and without
mimucal's template database (:func:`flows.runtime.seed_prefect_home`; "built by the
command": none yet, the command's server migrates the new home's database and
:func:`flows.runtime.save_prefect_template` copies it). The 1-minute load average at each
launch is printed with the medians: above the core count, other work shared the machine.

The heartbeat is off in every case (:func:`flows.runtime.run_settings`: ~1 s per flow run
when on)."""

from __future__ import annotations

import argparse
import json
import os
import resource
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from datetime import datetime
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

_CHILD = r"""
import json, time
t0 = time.perf_counter()
from flows import runtime
runtime.ensure_environment()
import prefect
from prefect import flow
t1 = time.perf_counter()

@flow(persist_result=False)
def empty():
    return 1

with runtime.run_settings():
    empty()
    t2 = time.perf_counter()
    empty()
    t3 = time.perf_counter()
print(json.dumps({"import": t1 - t0, "first_flow": t2 - t1, "second_flow": t3 - t2}))
"""


def run_case(home: Path, extra_env: dict[str, str] | None = None) -> dict[str, float]:
    env = {k: v for k, v in os.environ.items() if not k.startswith("PREFECT_")}
    env.update({"PREFECT_HOME": str(home), "PYTHONPATH": str(ROOT), **(extra_env or {})})
    t0 = time.perf_counter()
    out = subprocess.run(
        [sys.executable, "-c", _CHILD], env=env, cwd=ROOT, capture_output=True, text=True, check=True
    )
    wall = time.perf_counter() - t0
    doc = json.loads(out.stdout.strip().splitlines()[-1])
    doc["process"] = wall
    return doc


def _mimucal(args: list[str], env: dict[str, str]) -> tuple[float, float, float, float]:
    """(wall s, CPU s of the process tree, launch and end as epoch seconds)."""
    r0 = resource.getrusage(resource.RUSAGE_CHILDREN)
    launch, t0 = time.time(), time.perf_counter()
    subprocess.run(
        [sys.executable, "-m", "flows.cli", *args], env=env, cwd=ROOT, capture_output=True, text=True
    )
    wall, end = time.perf_counter() - t0, time.time()
    r1 = resource.getrusage(resource.RUSAGE_CHILDREN)
    cpu = (r1.ru_utime - r0.ru_utime) + (r1.ru_stime - r0.ru_stime)
    return wall, cpu, launch, end


def nightly_cases(n_units: int, repeats: int) -> dict[str, dict[str, float]]:
    """Median per case (new / existing home x no template / template built by the command /
    template present) of a whole ``mimucal nightly`` of ``n_units`` units: command wall, flow
    body, outside the flow, before and after the body, CPU of the process tree, load at
    launch (seconds)."""
    rows: dict[str, list[dict[str, float]]] = {}
    with tempfile.TemporaryDirectory(prefix="mimucal-prefect-bench-") as tmp:
        tmp = Path(tmp)
        env = {k: v for k, v in os.environ.items() if not k.startswith("PREFECT_")}
        env["PYTHONPATH"] = str(ROOT)
        _mimucal(["simulate", str(tmp / "ds"), "--units", str(n_units), "--reps", "5", "--seed", "3"], env)
        for i in range(repeats):
            for template in ("no template", "template built by the command", "template"):
                slug = template.replace(" ", "-")
                cache = tmp / f"cache-{slug}-{i}"
                if template == "template":  # built beforehand: what every later new home gets
                    shutil.copytree(tmp / f"cache-template-built-by-the-command-{i}", cache)
                run_env = {**env, "MIMUCAL_CACHE_DIR": str(cache)}
                if template == "no template":  # the server creates and migrates its database
                    run_env["MIMUCAL_PREFECT_TEMPLATE"] = "off"
                results = tmp / f"res-{slug}-{i}"
                for case, extra in (("new home", []), ("existing home", ["--force"])):
                    load = os.getloadavg()[0]
                    wall, cpu, launch, end = _mimucal(
                        ["nightly", str(tmp / "ds"), "--results", str(results), *extra], run_env
                    )
                    runs = sorted((results / "runs").glob("*.json"), key=lambda p: p.stat().st_mtime)
                    log = json.loads(runs[-1].read_text())
                    body = float(log["elapsed_s"])
                    start = datetime.fromisoformat(log["start"].replace("Z", "+00:00")).timestamp()
                    rows.setdefault(f"{case}, {template}", []).append(
                        {
                            "wall": wall,
                            "body": body,
                            "outside": wall - body,
                            "before": start - launch,
                            "after": end - (start + body),
                            "cpu": cpu,
                            "load": load,
                        }
                    )
    return {case: {k: statistics.median(r[k] for r in runs) for k in runs[0]} for case, runs in rows.items()}


def nightly_table(n_units: int, cases: dict[str, dict[str, float]]) -> list[str]:
    """The Markdown table of :func:`nightly_cases`."""
    out = [
        f"| {n_units}-unit nightly | command wall (s) | flow body (s) | outside the flow (s) "
        "| before the body (s) | after it (s) | CPU, process tree (s) | load at launch |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for case, med in cases.items():
        out.append(
            f"| {case} | {med['wall']:.1f} | {med['body']:.1f} | {med['outside']:.1f} "
            f"| {med['before']:.1f} | {med['after']:.1f} | {med['cpu']:.1f} | {med['load']:.1f} |"
        )
    return out


def nightly(n_units: int, repeats: int) -> int:
    print("\n".join(nightly_table(n_units, nightly_cases(n_units, repeats))))
    print(f"\nmedians of {repeats} run(s) each")
    return 0


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=2)
    ap.add_argument("--nightly", type=int, metavar="N", help="a whole nightly of N units instead")
    args = ap.parse_args(argv)
    if args.nightly:
        return nightly(args.nightly, args.repeats)
    rows: dict[str, list[dict[str, float]]] = {}
    with tempfile.TemporaryDirectory(prefix="mimucal-prefect-bench-") as tmp:
        tmp = Path(tmp)
        template = None
        for i in range(args.repeats):
            home = tmp / f"home{i}"
            home.mkdir()
            rows.setdefault("new home", []).append(run_case(home))
            rows.setdefault("existing home", []).append(run_case(home))
            rows.setdefault("existing home, no migrate check", []).append(
                run_case(home, {"PREFECT_SERVER_DATABASE_MIGRATE_ON_START": "false"})
            )
            template = home / "prefect.db"
            seeded = tmp / f"seeded{i}"
            seeded.mkdir()
            shutil.copy2(template, seeded / "prefect.db")
            rows.setdefault("new home, template db", []).append(run_case(seeded))
    print(
        "| case | import prefect (s) | first flow run: server start (s) "
        "| second flow run (s) | process wall (s) |"
    )
    print("|---|---|---|---|---|")
    for case, runs in rows.items():
        med = {k: statistics.median(r[k] for r in runs) for k in runs[0]}
        print(
            f"| {case} | {med['import']:.2f} | {med['first_flow']:.2f} | {med['second_flow']:.2f} "
            f"| {med['process']:.2f} |"
        )
    print(f"\nmedians of {args.repeats} run(s) each")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
