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

The heartbeat is off in every case (:func:`flows.runtime.run_settings`: ~1 s per flow run
when on)."""

from __future__ import annotations

import argparse
import json
import os
import shutil
import statistics
import subprocess
import sys
import tempfile
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
    t0 = __import__("time").perf_counter()
    out = subprocess.run(
        [sys.executable, "-c", _CHILD], env=env, cwd=ROOT, capture_output=True, text=True, check=True
    )
    wall = __import__("time").perf_counter() - t0
    doc = json.loads(out.stdout.strip().splitlines()[-1])
    doc["process"] = wall
    return doc


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=2)
    args = ap.parse_args(argv)
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
