"""``mimucal rerun DATASET --results DIR --unit UNIT``: recalibrate one unit now.

Its rows are replaced only if the recalibration succeeds; otherwise its last good calibration
is kept and marked stale (the units and summary tables) with the reason, and the exit code
is 1. Its lot's flags and report are rebuilt either way."""

from __future__ import annotations

import argparse
from pathlib import Path

from flows.cli import CliError
from flows.commands.nightly import CONFIG_HELP, check_config, exit_code, print_outcome

EPILOG = """examples:
  mimucal rerun data/fleet --results results --unit U0042"""


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "rerun",
        help="recalibrate one unit and replace only its results",
        description=__doc__,
        epilog=EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("dataset", metavar="DATASET", help="hive dataset root")
    p.add_argument("--results", required=True, metavar="DIR", help="results store directory")
    p.add_argument("--unit", required=True, help="unit id")
    p.add_argument("--config", metavar="TOML", default=None, help=CONFIG_HELP)
    p.add_argument("--wait", action="store_true", help="wait for a run holding the store")
    p.add_argument("--no-discovery", action="store_true", help="skip model discovery")
    p.add_argument(
        "--verbose",
        action="store_true",
        help="show Prefect's log lines on the terminal (default: RESULTS/logs/prefect.log)",
    )
    p.add_argument(
        "--follow-symlinks",
        action="store_true",
        help="read session directories and files, field recordings and options files "
        "reached through a symbolic link that stays inside DATASET (refused by default; "
        "a link leading outside DATASET is refused always)",
    )
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    if not Path(args.dataset).is_dir():
        raise CliError(f"dataset {args.dataset} is not a directory")
    check_config(args.config)
    from flows.user_errors import check_unit_in_dataset

    check_unit_in_dataset(args.dataset, args.unit)  # answered before Prefect starts
    from flows import runtime

    runtime.ensure_environment(args.results, verbose=args.verbose)
    runtime.start_api_server_early()  # while the store is checked and the flow's modules imported
    from schemas.results_store import ResultsStore, StoreLockedError

    if not args.wait:  # refused before the flow starts (the flow checks again)
        try:
            ResultsStore(Path(args.results)).ensure_unlocked()
        except StoreLockedError as exc:
            raise CliError(str(exc)) from None
    ResultsStore(Path(args.results)).check()
    from calib_core.outliers import OutlierConfigError
    from flows import nightly

    try:
        log = nightly.rerun_unit(
            args.dataset,
            args.results,
            args.unit,
            args.config,
            args.wait,
            run_discovery=not args.no_discovery,
            follow_symlinks=args.follow_symlinks,
        )
    except (StoreLockedError, OutlierConfigError, FileNotFoundError, LookupError) as exc:
        raise CliError(str(exc)) from None
    print_outcome(log)
    return exit_code(log)
