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
  temporary API server otherwise creates and migrates its database at start (its costliest
  part then, docs/benchmarks.md). The template is ``~/.cache/mimucal/prefect-<version>.db``
  (``$MIMUCAL_CACHE_DIR`` or ``$XDG_CACHE_HOME``): the database of the first new home whose
  command started the server (:func:`start_api_server_early`), copied once that server has
  migrated it and before any flow run (:func:`save_prefect_template`);
  ``MIMUCAL_PREFECT_TEMPLATE=off`` leaves every new home to the server.
- the ``nightly``, ``rerun`` and ``report`` commands start the temporary API server first
  (:func:`start_api_server_early`, :class:`TemporaryApiServer`): a subprocess running the same
  uvicorn command as Prefect's own, started without importing Prefect's server modules here,
  while this process checks the store and imports Prefect and the flow's modules; the flow
  waits for it to answer (:func:`await_api_server`) and every client of the run reaches it
  through ``PREFECT_API_URL``, set in the environment before ``import prefect``. It runs
  every service Prefect's temporary server runs (the task-run recorder and the event
  persister write the task runs' states and the events the UI shows); it is stopped, and
  waited for, at exit.
"""

from __future__ import annotations

import atexit
import os
import shutil
import subprocess
import sys
import tempfile
import threading
import time
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
        if not seed_prefect_home(home) and results is not None:
            _want_template(home)
    return Path(os.environ["PREFECT_HOME"])


PREFECT_DB = "prefect.db"  # the temporary API server's SQLite database, in PREFECT_HOME


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


def seed_prefect_home(home: Path) -> bool:
    """Copy the template database into a home that has none (True when copied). Any failure
    leaves the home as it was: the server then creates its database itself."""
    db = Path(home) / PREFECT_DB
    template = prefect_db_template()
    if template is None or db.exists() or os.environ.get("MIMUCAL_PREFECT_TEMPLATE") == "off":
        return False
    try:
        if not template.is_file():
            return False
        tmp = db.with_name(f".{db.name}.{os.getpid()}.tmp")
        shutil.copyfile(template, tmp)
        os.replace(tmp, db)
        return True
    except OSError:
        return False


_home_for_template: Path | None = None  # a new home whose migrated database makes the template


def _want_template(home: Path) -> None:
    """Remember a new home that got no template (none made yet): once the temporary server
    has migrated its database, :func:`save_prefect_template` copies it into the template."""
    global _home_for_template
    template = prefect_db_template()
    if (
        template is not None
        and not template.is_file()
        and os.environ.get("MIMUCAL_PREFECT_TEMPLATE") != "off"
    ):
        _home_for_template = Path(home)


def save_prefect_template(db: Path, template: Path | None = None) -> bool:
    """Copy the database ``db`` into the template (True when written) with SQLite's online
    backup: a consistent copy while the server has it open (WAL mode). Called when the server
    that migrated a new home's database answers, before any client wrote a flow run to it;
    an existing template is kept. Any failure leaves no template behind."""
    import sqlite3

    template = template or prefect_db_template()
    if template is None or template.exists() or not Path(db).is_file():
        return False
    tmp = template.with_name(f".{template.name}.{os.getpid()}.tmp")
    try:
        template.parent.mkdir(parents=True, exist_ok=True)
        src = sqlite3.connect(f"file:{db}?mode=ro", uri=True)
        try:
            dst = sqlite3.connect(tmp)
            try:
                src.backup(dst)
            finally:
                dst.close()
        finally:
            src.close()
        if template.exists():  # another command made it meanwhile: keep that one
            tmp.unlink()
            return False
        os.replace(tmp, template)
        return True
    except (OSError, sqlite3.Error):
        tmp.unlink(missing_ok=True)
        return False


class TemporaryApiServer:
    """Prefect's temporary API server, started by mimucal itself: the command that Prefect's
    ``SubprocessASGIServer`` runs (uvicorn, ``prefect.server.api.server:create_app``, the UI
    off, the same settings through the environment), launched without importing Prefect's
    server modules in this process (which the flow's client would otherwise import before
    starting the server). Its URL is meant for ``PREFECT_API_URL``
    (:func:`start_api_server_early`), so that no client of the run starts a server of its
    own."""

    def __init__(self) -> None:
        import socket
        from importlib.util import find_spec

        spec = find_spec("prefect")
        if spec is None or not spec.submodule_search_locations:
            raise RuntimeError("prefect is not installed")
        with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as sock:
            sock.bind(("127.0.0.1", 0))  # a free port, as the server's bind will see it
            self.port = sock.getsockname()[1]
        self.url = f"http://127.0.0.1:{self.port}/api"
        self.app_dir = Path(list(spec.submodule_search_locations)[0]).parent
        self.env = {k: v for k, v in os.environ.items() if k != "PREFECT_API_URL"}
        self.env.update(
            {"PREFECT_UI_ENABLED": "0", "PREFECT__SERVER_EPHEMERAL": "1", "PREFECT__SERVER_FINAL": "1"}
        )
        self.launch()
        atexit.register(self.stop)

    def launch(self) -> None:
        self.process = subprocess.Popen(
            [
                sys.executable, "-m", "uvicorn", "--app-dir", str(self.app_dir), "--factory",
                "prefect.server.api.server:create_app", "--host", "127.0.0.1", "--port",
                str(self.port), "--log-level", "error", "--lifespan", "on",
            ],
            env=self.env,
        )  # fmt: skip

    def wait_healthy(self, timeout: float) -> bool:
        """Poll ``/api/health`` until it answers 200 (True) or the server exits or the
        timeout passes (False)."""
        import http.client

        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            if self.process.poll() is not None:
                return False
            conn = http.client.HTTPConnection("127.0.0.1", self.port, timeout=5)
            try:
                conn.request("GET", "/api/health")
                if conn.getresponse().status == 200:
                    return True
            except OSError:
                pass
            finally:
                conn.close()
            time.sleep(0.05)
        return False

    def stop(self) -> None:
        """Terminate the server and wait for its shutdown (as Prefect's own stop: the server
        stops its services, which write the events they hold, before it exits)."""
        if self.process.poll() is None:
            self.process.terminate()
            try:
                self.process.wait(timeout=5)
            except subprocess.TimeoutExpired:
                self.process.kill()
                self.process.wait()


_early_server: TemporaryApiServer | None = None  # started by this process, not yet awaited
_early_thread: threading.Thread | None = None  # Prefect's own server starting in a thread
_api_server: TemporaryApiServer | None = None  # answered its health check


def _falsy(value: str | None) -> bool:
    return (value or "").strip().lower() in ("0", "false", "no", "off")


def _prefect_configuration_in_reach() -> bool:
    """Whether a Prefect configuration file that may name an API server is read by this
    process's Prefect: the home's profiles (or ``PREFECT_PROFILES_PATH``), or ``prefect.toml``,
    ``.env`` or a ``pyproject.toml`` with ``[tool.prefect]`` in the working directory."""
    home = Path(os.environ.get("PREFECT_HOME") or Path.home() / ".prefect")
    profiles = Path(os.environ.get("PREFECT_PROFILES_PATH") or home / "profiles.toml")
    if Path("prefect.toml").is_file():
        return True
    for path, mark in (
        (profiles, "PREFECT_API_URL"),
        (Path(".env"), "PREFECT_"),
        (Path("pyproject.toml"), "tool.prefect"),
    ):
        try:
            if mark in path.read_text(errors="replace"):
                return True
        except OSError:
            pass
    return False


def start_api_server_early() -> None:
    """Start the temporary API server now, while the command checks the store and imports
    Prefect and the flow's modules; nothing when a real server's ``PREFECT_API_URL`` is in the
    environment or the temporary server is off.

    Before ``import prefect``, and with no Prefect configuration file in reach: a
    :class:`TemporaryApiServer`, whose URL goes into ``PREFECT_API_URL`` in the environment, so
    that Prefect's settings give it to every client of the run (the flow's, its background
    threads', worker processes'). Otherwise (Prefect imported already, as in a test process,
    or its configuration to be read by Prefect): Prefect's own temporary server, started in a
    daemon thread (the object the flow's first client would start: one per process); a
    failure there is left to the flow, whose client starts it again and says why."""
    global _early_server, _early_thread
    if _early_server is not None or _early_thread is not None or _api_server is not None:
        return
    if os.environ.get("PREFECT_API_URL") or _falsy(os.environ.get("PREFECT_SERVER_EPHEMERAL_ENABLED")):
        return
    if "prefect" not in sys.modules and not _prefect_configuration_in_reach():
        try:
            server = TemporaryApiServer()
        except (OSError, RuntimeError):
            return
        os.environ["PREFECT_API_URL"] = server.url
        _early_server = server
        return
    from prefect.settings import PREFECT_API_URL, PREFECT_SERVER_EPHEMERAL_ENABLED

    if PREFECT_API_URL.value() or not PREFECT_SERVER_EPHEMERAL_ENABLED.value():
        return

    def start() -> None:
        from prefect.server.api.server import SubprocessASGIServer

        try:
            SubprocessASGIServer().start()
        except Exception:  # noqa: BLE001 - the flow's client starts it again and says why
            pass

    _early_thread = threading.Thread(target=start, name="mimucal-api-start", daemon=True)
    _early_thread.start()


def await_api_server() -> None:
    """Wait for :func:`start_api_server_early`'s server to answer (nothing when not started).
    A :class:`TemporaryApiServer` that exits or does not answer is started once more on its
    port (the URL Prefect has); a second failure raises ``RuntimeError``. When a new home's
    server answers, its migrated database becomes the template (:func:`save_prefect_template`)."""
    global _early_server, _early_thread, _api_server, _home_for_template
    thread, _early_thread = _early_thread, None
    if thread is not None:
        thread.join()
    server, _early_server = _early_server, None
    if server is None:
        return
    timeout = float(os.environ.get("PREFECT_SERVER_EPHEMERAL_STARTUP_TIMEOUT_SECONDS") or 300)
    if not server.wait_healthy(timeout):
        server.stop()
        server.launch()
        if not server.wait_healthy(timeout):
            code = server.process.poll()
            server.stop()
            raise RuntimeError(
                f"Prefect's temporary API server at {server.url} did not start"
                + (f" (exit code {code})" if code is not None else f" within {timeout:g} s")
            )
    _api_server = server
    home, _home_for_template = _home_for_template, None
    if home is not None:  # its server migrated it: the template for the next new homes
        save_prefect_template(home / PREFECT_DB)


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
