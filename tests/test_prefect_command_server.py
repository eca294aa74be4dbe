"""``mimucal nightly`` as a user runs it (its own process): the command starts Prefect's
temporary API server itself (flows.runtime.TemporaryApiServer) and no client of the run starts
another (the flow's, its threads', Prefect's worker processes'), its flow and task runs are
recorded with their final states in the home's database (task-run states go through the
server's event pipeline: the services it runs are the ones it needs), the first new home's
migrated database becomes the template, and the process ends with the command's exit code
and its complete output without the interpreter's finalization (flows.cli.entry)."""

from __future__ import annotations

import os
import sqlite3
import subprocess
import sys
from pathlib import Path

import pytest

from flows.fleet_sim import simulate_fleet

REPO = Path(__file__).resolve().parent.parent


def _env(tmp_path: Path) -> dict[str, str]:
    env = {k: v for k, v in os.environ.items() if not k.startswith(("PREFECT_", "MIMUCAL_"))}
    env.update({"PYTHONPATH": str(REPO), "MIMUCAL_CACHE_DIR": str(tmp_path / "cache")})
    return env


def _mimucal(args: list[str], env: dict[str, str]) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", "flows.cli", *args],
        cwd=REPO,
        env=env,
        capture_output=True,
        text=True,
        timeout=300,
    )


def test_exit_code_and_output_survive_the_fast_exit(tmp_path):
    env = _env(tmp_path)
    out = _mimucal(["--help"], env)
    assert out.returncode == 0  # the whole help, its last words included, reached the pipe
    assert " ".join(out.stdout.split()).endswith("--debug (anywhere) shows tracebacks.")
    out = _mimucal(["nightly", str(tmp_path / "missing"), "--results", str(tmp_path / "r")], env)
    assert out.returncode == 2
    assert out.stderr.strip() == f"mimucal nightly: error: dataset {tmp_path / 'missing'} is not a directory"


@pytest.mark.server
@pytest.mark.slow
def test_a_nightly_on_a_new_home_records_its_runs_and_makes_the_template(tmp_path):
    data, results = tmp_path / "data", tmp_path / "results"
    simulate_fleet(data, lots=1, units=3, reps=2, seed=11, sample_rate_hz=20.0)
    env = _env(tmp_path)
    # Prefect's process pool: task runs in worker processes, their events forwarded by a
    # thread of the flow's process; every one of them must reach the command's server
    args = ["--no-discovery", "--batch-size", "1", "--runner", "prefect-processes"]
    out = _mimucal(["nightly", str(data), "--results", str(results), *args], env)
    assert out.returncode == 0, out.stderr
    assert "3 units (3 calibrated" in out.stdout
    assert "Starting temporary server" not in (results / "logs" / "prefect.log").read_text()
    home_db = results / ".prefect" / "prefect.db"
    con = sqlite3.connect(home_db)
    assert [r[0] for r in con.execute("SELECT name FROM flow")] == ["nightly-fleet-calibration"]
    assert con.execute("SELECT state_type FROM flow_run").fetchall() == [("COMPLETED",)]
    assert con.execute("SELECT state_type, count(*) FROM task_run GROUP BY state_type").fetchall() == [
        ("COMPLETED", 3)
    ]
    con.close()
    templates = list((tmp_path / "cache").glob("prefect-*.db"))
    assert len(templates) == 1
    tpl = sqlite3.connect(templates[0])
    assert tpl.execute("SELECT count(*) FROM alembic_version").fetchone() == (1,)
    assert tpl.execute("SELECT count(*) FROM flow_run").fetchone() == (0,)  # made before the run
    tpl.close()


def test_a_prefect_configuration_in_reach_leaves_the_server_to_prefect(tmp_path, monkeypatch):
    from flows import runtime

    home = tmp_path / "home"
    home.mkdir()
    monkeypatch.chdir(tmp_path)
    monkeypatch.setenv("PREFECT_HOME", str(home))
    monkeypatch.delenv("PREFECT_PROFILES_PATH", raising=False)
    assert not runtime._prefect_configuration_in_reach()
    (home / "profiles.toml").write_text('[profiles.default]\nPREFECT_API_URL = "http://lab:4200/api"\n')
    assert runtime._prefect_configuration_in_reach()
    (home / "profiles.toml").unlink()
    (tmp_path / "pyproject.toml").write_text('[project]\nname = "x"\n')
    assert not runtime._prefect_configuration_in_reach()
    (tmp_path / "pyproject.toml").write_text('[tool.prefect.api]\nurl = "http://lab:4200/api"\n')
    assert runtime._prefect_configuration_in_reach()
    (tmp_path / "pyproject.toml").unlink()
    (tmp_path / "prefect.toml").write_text('[api]\nurl = "http://lab:4200/api"\n')
    assert runtime._prefect_configuration_in_reach()
