"""Prefect settings for mimucal runs: local, quiet, offline, no sample data persisted.

Prefect reads most settings from the environment when it is imported, so
:func:`ensure_environment` must run before ``import prefect`` (the CLI commands call it first
and import :mod:`flows.nightly` afterwards; :mod:`flows.nightly` calls it at import with no
results directory). Values the user already set in the environment win.

- ``PREFECT_HOME``: ``<results>/.prefect`` (the temporary local API's SQLite lives there), or a
  fresh temp directory when no results directory is known (``import prefect`` alone creates
  its home; a read-only ``~`` would make it fail after ~23 s).
- ``PREFECT_SERVER_ANALYTICS_ENABLED=false``, ``DO_NOT_TRACK=1``: no telemetry, no DNS lookup.
- ``PREFECT_LOGGING_LEVEL=WARNING``: no per-task INFO lines.
- ``PREFECT_RESULTS_PERSIST_BY_DEFAULT=false``: task results (which never hold samples: tasks
  take paths) are not written to disk; the results store is the record.
- Prefect's own log lines (flow and task states, its warnings) go to ``<results>/logs/prefect.log``
  at INFO level, not to the terminal, where mimucal prints its own progress and outcome lines;
  ``verbose=True`` (the commands' ``--verbose``) leaves Prefect's console logging on, at INFO.
  A ``PREFECT_LOGGING_SETTINGS_PATH`` of the user's wins.
- the flow-run heartbeat is switched off with :func:`run_settings` (the environment cannot
  say "off"); it costs ~1 s per flow run when on.
- a new home gets a copy of a migrated, empty ``prefect.db`` (:func:`seed_prefect_home`): the
  temporary API server otherwise creates and migrates its database at start (~7.5 s CPU, 8-30 s
  wall on a loaded 2-core machine, benchmarks/prefect_startup.py). The template is
  ``~/.cache/mimucal/prefect-<version>.db`` (``$MIMUCAL_CACHE_DIR`` or ``$XDG_CACHE_HOME``),
  built once per Prefect version by the first command that has a results directory;
  ``MIMUCAL_PREFECT_TEMPLATE=off`` leaves new homes to the server.
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import tempfile
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

_DEFAULTS = {
    "PREFECT_SERVER_ANALYTICS_ENABLED": "false",
    "DO_NOT_TRACK": "1",
    "PREFECT_LOGGING_LEVEL": "WARNING",
    "PREFECT_RESULTS_PERSIST_BY_DEFAULT": "false",
    "PREFECT_TASKS_DEFAULT_PERSIST_RESULT": "false",
    # a new database is migrated at first start: 30-55 s seen on a loaded 2-core machine
    "PREFECT_SERVER_EPHEMERAL_STARTUP_TIMEOUT_SECONDS": "300",
    "PREFECT_CLI_COLORS": "false",
}


PREFECT_LOG = Path("logs") / "prefect.log"  # under the results directory


def ensure_environment(results: Path | str | None = None, verbose: bool = False) -> Path:
    """Set mimucal's Prefect environment defaults; return PREFECT_HOME. With a results
    directory, Prefect's log lines go to its :data:`PREFECT_LOG` unless ``verbose``."""
    if verbose:
        os.environ.setdefault("PREFECT_LOGGING_LEVEL", "INFO")
    elif results is not None:
        route_prefect_logs(Path(results).resolve() / PREFECT_LOG)
    for k, v in _DEFAULTS.items():
        os.environ.setdefault(k, v)
    if "PREFECT_HOME" not in os.environ:
        if results is not None:
            home = Path(results).resolve() / ".prefect"
        else:
            home = Path(tempfile.mkdtemp(prefix="mimucal-prefect-"))
        home.mkdir(parents=True, exist_ok=True)
        os.environ["PREFECT_HOME"] = str(home)
        seed_prefect_home(home, build=results is not None)
    return Path(os.environ["PREFECT_HOME"])


PREFECT_DB = "prefect.db"  # the temporary API server's SQLite database, in PREFECT_HOME

_BUILD_TEMPLATE = """
import asyncio
from prefect.server.database import provide_database_interface
asyncio.run(provide_database_interface().create_db())
"""


def prefect_db_template() -> Path | None:
    """Where the migrated, empty database of the installed Prefect version is kept (None:
    Prefect is not installed)."""
    from importlib.metadata import PackageNotFoundError, version

    try:
        v = version("prefect")
    except PackageNotFoundError:
        return None
    base = os.environ.get("MIMUCAL_CACHE_DIR") or os.path.join(
        os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache"), "mimucal"
    )
    return Path(base) / f"prefect-{v}.db"


def seed_prefect_home(home: Path, build: bool = False) -> bool:
    """Copy the template database into a home that has none (True when copied). ``build``:
    make the template first when it is missing (a subprocess migrates an empty database in a
    scratch home; held by a lock so that concurrent commands build it once). Any failure
    leaves the home as it was: the server then creates its database itself."""
    db = Path(home) / PREFECT_DB
    template = prefect_db_template()
    if template is None or db.exists() or os.environ.get("MIMUCAL_PREFECT_TEMPLATE") == "off":
        return False
    try:
        if not template.is_file() and build:
            _build_template(template)
        if not template.is_file():
            return False
        tmp = db.with_name(f".{db.name}.{os.getpid()}.tmp")
        shutil.copyfile(template, tmp)
        os.replace(tmp, db)
        return True
    except (OSError, subprocess.SubprocessError):
        return False


def _build_template(template: Path) -> None:
    import fcntl

    template.parent.mkdir(parents=True, exist_ok=True)
    with open(template.with_name(template.name + ".lock"), "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)  # another command building it: wait, then use it
        if template.is_file():
            return
        with tempfile.TemporaryDirectory(prefix="mimucal-prefect-template-", dir=template.parent) as scratch:
            env = {k: v for k, v in os.environ.items() if not k.startswith("PREFECT_")}
            env.update(
                {"PREFECT_HOME": scratch, "DO_NOT_TRACK": "1", "PREFECT_SERVER_ANALYTICS_ENABLED": "false"}
            )
            subprocess.run(
                [sys.executable, "-c", _BUILD_TEMPLATE],
                env=env,
                check=True,
                capture_output=True,
                timeout=600,
            )
            os.replace(Path(scratch) / PREFECT_DB, template)


def route_prefect_logs(log_file: Path) -> Path | None:
    """Write a Prefect logging configuration whose console handlers write to ``log_file``
    (Prefect's own configuration otherwise) and point ``PREFECT_LOGGING_SETTINGS_PATH`` at it;
    must run before ``import prefect``. Returns the configuration's path, None when the user
    set one."""
    if "PREFECT_LOGGING_SETTINGS_PATH" in os.environ:
        return None
    from importlib.util import find_spec

    import yaml  # a dependency of Prefect's

    spec = find_spec("prefect")
    if spec is None or not spec.submodule_search_locations:
        return None
    default = Path(list(spec.submodule_search_locations)[0]) / "logging" / "logging.yml"
    config = yaml.safe_load(default.read_text())
    log_file.parent.mkdir(parents=True, exist_ok=True)
    to_file = {
        "level": 0,
        "class": "logging.FileHandler",
        "filename": str(log_file),
        "encoding": "utf-8",
        "delay": True,
    }
    handlers = config.setdefault("handlers", {})
    handlers["console"] = {**to_file, "formatter": "standard"}
    handlers["debug"] = {**to_file, "formatter": "debug"}
    os.environ.setdefault("PREFECT_LOGGING_LEVEL", "INFO")  # the file keeps the whole story
    path = log_file.parent / ".prefect-logging.yml"
    tmp = path.with_name(path.name + f".{os.getpid()}.tmp")
    tmp.write_text(yaml.safe_dump(config, sort_keys=False))
    os.replace(tmp, path)
    os.environ["PREFECT_LOGGING_SETTINGS_PATH"] = str(path)
    return path


@contextmanager
def run_settings(api_url: str | None = None) -> Iterator[None]:
    """Settings that cannot be set through the environment (heartbeat off) and, optionally,
    the API of a real server."""
    ensure_environment()
    from prefect.settings import PREFECT_API_URL, PREFECT_FLOWS_HEARTBEAT_FREQUENCY, temporary_settings

    updates = {PREFECT_FLOWS_HEARTBEAT_FREQUENCY: None}
    if api_url:
        updates[PREFECT_API_URL] = api_url
    with temporary_settings(updates=updates):
        yield


def code_version() -> str:
    """``mimucal <version>`` plus the git commit of the working tree when there is one (read
    from .git, no subprocess)."""
    try:
        from importlib.metadata import version

        v = version("mimucal")
    except Exception:
        v = "0.1.0"
    git = Path(__file__).resolve().parent.parent / ".git"
    try:
        head = (git / "HEAD").read_text().strip()
        if head.startswith("ref:"):
            ref = head.split(None, 1)[1]
            p = git / ref
            if p.exists():
                sha = p.read_text().strip()
            else:
                sha = next(
                    (
                        line.split()[0]
                        for line in (git / "packed-refs").read_text().splitlines()
                        if line.endswith(ref)
                    ),
                    "",
                )
        else:
            sha = head
        if sha:
            return f"mimucal {v}+g{sha[:10]}"
    except OSError:
        pass
    return f"mimucal {v}"
