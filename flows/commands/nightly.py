"""``mimucal nightly DATASET --results DIR``: calibrate what is new or changed, flag, report."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from flows.cli import CliError

EPILOG = """examples:
  mimucal nightly data/fleet --results results
  mimucal nightly data/fleet --results results --force --config limits.toml
  mimucal nightly data/fleet --results results --dask-address tcp://10.0.0.5:8786
  mimucal nightly data/fleet --results results --runner threads

Sessions whose content fingerprint (an XXH3-128 digest of both files' bytes) is unchanged
since the last run are skipped; a unit with any new, changed or removed session is recalibrated as a whole.
Prints a progress line per lot as its units come back ("lot L01: 8/16 units, 3.2 s") and a
one-line summary with the wall time since the command started; the run log is
RESULTS/runs/<run_id>.json, Prefect's own log RESULTS/logs/prefect.log (--verbose: on the
terminal) and the reports RESULTS/reports/."""


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "nightly",
        help="calibrate every new or changed session of a fleet",
        description=__doc__,
        epilog=EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("dataset", metavar="DATASET", help="hive dataset root (lot=/unit=/rep=)")
    p.add_argument("--results", required=True, metavar="DIR", help="results store directory")
    p.add_argument("--force", action="store_true", help="recalibrate every unit")
    p.add_argument(
        "--dask-address",
        metavar="ADDR",
        default=None,
        help="run the per-unit tasks on this Dask scheduler (tcp://host:port)",
    )
    p.add_argument(
        "--runner",
        default=None,
        choices=["auto", "threads", "processes", "prefect-processes", "dask"],
        help="where the unit work runs without --dask-address: auto (default: "
        "worker processes from 24 units to calibrate, else threads), threads "
        "(one core), processes (a forkserver pool, both cores, ~3 s start-up), "
        "prefect-processes (Prefect's process pool), dask (a local Dask "
        "cluster); default $MIMUCAL_TASK_RUNNER or auto",
    )
    p.add_argument("--config", metavar="TOML", default=None, help=CONFIG_HELP)
    p.add_argument(
        "--batch-size", type=int, default=None, metavar="N", help="units per Prefect task (default 8)"
    )
    p.add_argument(
        "--wait",
        action="store_true",
        help="wait for another run holding the results store instead of refusing",
    )
    p.add_argument("--no-discovery", action="store_true", help="skip model discovery")
    p.add_argument("--quiet", action="store_true", help="no progress lines")
    p.add_argument(
        "--unit-reports",
        action="store_true",
        help="also write a report per unit of the lots reported (RESULTS/reports/units/; "
        "~0.2 s and ~5 MB each)",
    )
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


CONFIG_HELP = (
    "QA configuration: outlier options and acceptance limits with units (docs/"
    "flows.md); stored in the results store and applied by every later run; "
    "'none' clears it"
)


def check_config(path: str | None) -> None:
    """A ``--config`` refused before any orchestration starts: a missing file, TOML that does
    not parse, unknown parameters or units (one line naming the valid ones)."""
    if path is None or path == "none":
        return
    from schemas.limits import LimitsError, config_from_toml

    try:
        text = Path(path).read_text()
    except OSError as exc:
        raise CliError(f"configuration {path}: {exc.strerror or exc}") from None
    try:
        config_from_toml(text, source=str(path))
    except LimitsError as exc:
        raise CliError(str(exc)) from None


def run(args: argparse.Namespace) -> int:
    dataset = Path(args.dataset)
    if not dataset.is_dir():
        raise CliError(f"dataset {dataset} is not a directory")
    check_config(args.config)
    if args.batch_size is not None and args.batch_size < 1:
        raise CliError("--batch-size must be >= 1")
    from flows import runtime

    runtime.ensure_environment(args.results, verbose=args.verbose)  # before Prefect's import
    # the API server starts first (~3 s of imports in its own process): meanwhile this one
    # checks the store and imports Prefect and the flow's modules; a refused command stops it
    runtime.start_api_server_early()
    from schemas.results_store import ResultsStore, StoreLockedError

    if not args.wait:  # refused before the flow starts (the flow checks again)
        ResultsStore(Path(args.results)).ensure_unlocked()
    ResultsStore(Path(args.results)).check()
    from flows.task_runners import resolve_kind

    try:
        resolve_kind(args.runner)  # a bad $MIMUCAL_TASK_RUNNER is refused before the flow
    except ValueError as exc:
        raise CliError(str(exc)) from None
    from calib_core.outliers import OutlierConfigError
    from flows import nightly

    try:
        log = nightly.nightly_fleet_calibration(
            dataset,
            args.results,
            force=args.force,
            dask_address=args.dask_address,
            batch_size=args.batch_size or nightly.DEFAULT_BATCH_SIZE,
            config=args.config,
            wait=args.wait,
            run_discovery=not args.no_discovery,
            progress=not args.quiet,
            runner=args.runner,
            unit_reports=args.unit_reports,
            follow_symlinks=args.follow_symlinks,
        )
    except (StoreLockedError, OutlierConfigError, FileNotFoundError) as exc:
        raise CliError(str(exc)) from None
    print_outcome(log)
    if not log.get("units_found") and not log.get("path_errors"):
        print(
            f"mimucal nightly: warning: no session under {dataset} (expected "
            f"lot=<id>/unit=<id>/rep=<n>/ or lot=<id>/unit=<id>/field/ directories); nothing to do",
            file=sys.stderr,
        )
        return 3
    return exit_code(log)


def exit_code(log: dict) -> int:
    """1 when any session, unit or report failed, or a directory did not parse; else 0 (5,
    the run failed unexpectedly, is flows.cli's)."""
    from flows.nightly import run_had_failures

    return 1 if run_had_failures(log) else 0


def print_outcome(log: dict) -> None:
    """The run's failures, flags and report problems, then its summary with the wall time
    since the command started (imports and Prefect's start-up included)."""
    for f in log.get("failed_sessions", []):
        print(f"failed session {f['session']}: {f['message']}", file=sys.stderr)
    for e in log.get("unit_errors", []):
        print(f"failed unit {e['unit']}: {e['message']}", file=sys.stderr)
    for e in log.get("path_errors", []):
        print(f"bad path: {e.get('message')}", file=sys.stderr)
    for unit, why in (log.get("units_stale") or {}).items():
        print(f"stale: {unit}: {why} (last good calibration kept)", file=sys.stderr)
    for lf in log.get("flags", []):
        for f in lf.get("flags", []):
            print(f"flag {f['lot']}/{f['unit']}: [{f['kind']}] {f['reason']}")
    for p in log.get("report_problems", []):
        print(f"report: {p}", file=sys.stderr)
    for n in log.get("protocol_notes", []):  # once per lot: a fact of its protocol
        print(f"protocol of lot {n['lot']}: {n['note']} ({n['sessions']} session(s), {n['units']} unit(s))")
    print(summary_with_wall_time(log))
    reports = log.get("reports") or []
    units = [r for r in reports if Path(r).parent.name == "units"]
    others = [r for r in reports if r not in units]
    if others:
        print("reports: " + ", ".join(others))
    if len(units) > 3:
        print(f"unit reports: {len(units)} in {Path(units[0]).parent}")
    elif units:
        print("unit reports: " + ", ".join(units))


def summary_with_wall_time(log: dict) -> str:
    """The run's summary line, its time being the command's wall time (the flow's own time
    in brackets)."""
    from flows.clock import since_start
    from flows.nightly import summary_line

    return summary_line(log, wall_s=since_start())
