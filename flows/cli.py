"""The ``mimucal`` command line: discovers subcommands in :mod:`flows.commands`."""
from __future__ import annotations

import argparse
import importlib
import pkgutil
import sys

from flows import commands


class CliError(Exception):
    """An error the user can fix: printed without a traceback, exit code 2."""


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="mimucal",
        description="Calibrate fleets of MEMS IMUs from turntable acquisitions.",
    )
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    sub.required = True
    for info in sorted(pkgutil.iter_modules(commands.__path__), key=lambda m: m.name):
        module = importlib.import_module(f"flows.commands.{info.name}")
        if hasattr(module, "register"):
            module.register(sub)
    from flows.help_text import clean_help
    clean_help(parser)
    return parser


def main(argv: list[str] | None = None) -> int:
    try:
        return _run(argv)
    except BrokenPipeError:  # the reader went away (``mimucal ... | head``): end quietly
        from flows.pipes import closed_pipe_exit
        return closed_pipe_exit()


def _run(argv: list[str] | None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        return int(args.func(args) or 0)
    except CliError as exc:
        print(f"mimucal {args.command}: error: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    # `python -m flows.cli`: call the importable module's main, so that CliError raised by
    # the commands is the same class main() catches (not __main__.CliError)
    from flows.cli import main as _main

    sys.exit(_main())
