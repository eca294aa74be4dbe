"""The ``mimucal`` command line: discovers subcommands in :mod:`flows.commands`.

Every failure is one line on stderr, ``mimucal <command>: error: <cause>``, and an exit code
(README, "Exit codes"): 0 all good, 1 some sessions, units or reports failed (or the run
itself failed unexpectedly), 2 a usage error or a store that cannot be used (damaged,
read-only, full, locked), 3 nothing to do (e.g. an empty dataset; a warning says so).
``--debug`` (anywhere on the line) shows the traceback and the numerical warnings instead.
"""

from __future__ import annotations

import argparse
import errno
import importlib
import os
import pkgutil
import sys
import warnings

from flows import commands

EXIT_OK, EXIT_FAILURES, EXIT_USAGE, EXIT_NOTHING_TO_DO = 0, 1, 2, 3
EXIT_RUN_FAILED = 5  # the run failed unexpectedly (a bug, Prefect down): not "some units failed"
_ID_ARGUMENTS = (("unit", "unit"), ("lot", "lot"))


class CliError(Exception):
    """An error the user can fix: printed without a traceback, exit code 2."""


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="mimucal",
        description="Calibrate fleets of MEMS IMUs from turntable acquisitions.",
        epilog="exit codes: 0 all good, 1 some sessions/units/reports failed, 2 usage or "
        "store error, 3 nothing to do. --debug (anywhere) shows tracebacks.",
    )
    parser.add_argument("--debug", action="store_true", help="show tracebacks and numerical warnings")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    sub.required = True
    for info in sorted(pkgutil.iter_modules(commands.__path__), key=lambda m: m.name):
        module = importlib.import_module(f"flows.commands.{info.name}")
        if hasattr(module, "register"):
            module.register(sub)
    from flows.help_text import clean_help

    clean_help(parser)
    return parser


def check_id_arguments(args: argparse.Namespace) -> None:
    """Every ``--unit``/``--lot`` goes through the check directory names go through
    (schemas.dataset.check_id): a name the store uses as a path must be one."""
    from schemas.dataset import check_id

    for attr, field in _ID_ARGUMENTS:
        value = getattr(args, attr, None)
        if isinstance(value, str):
            try:
                check_id(value, field)
            except ValueError as exc:
                raise CliError(f"--{attr}: {exc}") from None


def describe_os_error(exc: OSError) -> str:
    """One line for a file-system failure: what, where, and the errno's name."""
    name = errno.errorcode.get(exc.errno or 0, "")
    where = f" {exc.filename}" if exc.filename else ""
    hint = {
        errno.ENOSPC: "free space on that file system and run again",
        errno.EDQUOT: "free space (quota) and run again",
        errno.EROFS: "the file system is read-only; use a writable --results folder",
        errno.EACCES: "check the folder's permissions",
        errno.EPERM: "check the folder's permissions",
    }.get(exc.errno or 0)
    return (
        f"cannot write or read{where}: {exc.strerror or exc}"
        f"{f' ({name})' if name else ''}{f'; {hint}' if hint else ''}"
    )


def main(argv: list[str] | None = None) -> int:
    try:
        return _run(argv)
    except BrokenPipeError:  # the reader went away (``mimucal ... | head``): end quietly
        from flows.pipes import closed_pipe_exit

        return closed_pipe_exit()


def _run(argv: list[str] | None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    debug = "--debug" in argv
    argv = [a for a in argv if a != "--debug"]
    if not debug:
        # numerical warnings (overflow, empty slices) are the code's to handle and name, not
        # the user's terminal's; worker processes inherit the filter through the environment
        warnings.filterwarnings("ignore", category=RuntimeWarning)
        os.environ.setdefault("PYTHONWARNINGS", "ignore::RuntimeWarning")
    parser = build_parser()
    args = parser.parse_args(argv)
    args.debug = debug
    from schemas.results_store import StoreError, StoreLockedError

    try:
        check_id_arguments(args)
        return int(args.func(args) or 0)
    except (CliError, StoreError, StoreLockedError) as exc:
        if debug:
            raise
        print(f"mimucal {args.command}: error: {exc}", file=sys.stderr)
        return EXIT_USAGE
    except BrokenPipeError:
        raise  # main() ends quietly
    except OSError as exc:
        if debug:
            raise
        print(f"mimucal {args.command}: error: {describe_os_error(exc)}", file=sys.stderr)
        return EXIT_USAGE
    except KeyboardInterrupt:
        print(f"mimucal {args.command}: interrupted", file=sys.stderr)
        return 130
    except Exception as exc:  # noqa: BLE001 - Prefect or a bug: one line, trace with --debug
        if debug:
            raise
        cause = f"{type(exc).__name__}: {exc}".splitlines()[0]
        print(
            f"mimucal {args.command}: error: the run failed: {cause} (the store keeps its "
            f"last good state; --debug shows the traceback)",
            file=sys.stderr,
        )
        return EXIT_RUN_FAILED


_EXIT_CODE: list[int] = []  # the code entry() ends the process with, once main() returned


def _end_without_finalizing() -> None:
    """The last exit handler: end the process with main()'s code, skipping the interpreter's
    finalization (freeing every module and object, a second after a nightly). It runs after the
    non-daemon threads were joined and Prefect's event and log queues drained, and after
    every other exit handler (registered later: the API server's stop, multiprocessing's,
    logging's): what is left to do is only freeing memory."""
    if not _EXIT_CODE:
        return
    for stream in (sys.stdout, sys.stderr):
        try:
            stream.flush()
        except (OSError, ValueError):
            pass
    os._exit(_EXIT_CODE[0])


def entry() -> None:
    """The ``mimucal`` program: :func:`main`, then the process ends without the interpreter's
    finalization (:func:`_end_without_finalizing`)."""
    import atexit

    atexit.register(_end_without_finalizing)  # first registered: runs last
    try:
        code = main()
    except SystemExit as exc:  # argparse's usage errors and --help
        code = exc.code
    if code is None or isinstance(code, int):
        _EXIT_CODE.append(int(code or 0))
    sys.exit(code)


if __name__ == "__main__":
    # `python -m flows.cli`: call the importable module's entry, so that CliError raised by
    # the commands is the same class main() catches (not __main__.CliError)
    from flows.cli import entry as _entry

    _entry()
