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
"""

from __future__ import annotations

import os
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
    return Path(os.environ["PREFECT_HOME"])


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
