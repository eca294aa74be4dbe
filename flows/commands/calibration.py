"""``mimucal calibration --results DIR --unit U [--at ISO]``: the calibration file valid for a
unit at a date (as imucal's ``find_closest_calibration_info_to_date``).

Times are when the unit was measured (its sessions' ``session_start``; when absent, when the
calibration was produced, and the listing says so). Default: the latest calibration of a
measurement at or before ``--at`` (default now, UTC; a date alone means the end of that day);
``--mode after`` the earliest at or after (a date alone: its start), ``--mode closest`` the
nearest.

A unit whose calibration was judged ``flagged`` (an outlier in its lot) or ``limits`` (a
limit failed) is refused with exit code 4 and the reasons on stderr, unless
``--allow-flagged`` (then the reasons are printed on stderr and the path on stdout)."""

from __future__ import annotations

import argparse
import re
import sys
from datetime import timedelta

from flows.cli import CliError

EXIT_FLAGGED = 4  # the calibration found was judged flagged or outside limits

EPILOG = """examples:
  mimucal calibration --results results --unit U0001
  mimucal calibration --results results --unit U0001 --at 2026-11-20T12:00:00Z
  mimucal calibration --results results --unit U0001 --at 2026-11-20 --mode closest --list
  mimucal calibration --results results --unit U0007 --allow-flagged

exit codes: 0 found (QA pass, not judged, or --allow-flagged), 2 not found or bad
arguments, 4 refused: its QA status is flagged or limits"""


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "calibration",
        help="find the calibration file valid for a unit at a date",
        description=__doc__,
        epilog=EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("--results", required=True, metavar="DIR", help="results store directory")
    p.add_argument("--unit", required=True, help="unit id")
    p.add_argument(
        "--at", default=None, metavar="ISO", help="ISO 8601 date or date-time (UTC if no offset); default now"
    )
    p.add_argument("--mode", choices=("before", "after", "closest"), default="before")
    p.add_argument("--list", action="store_true", help="also list every calibration of the unit")
    p.add_argument(
        "--allow-flagged",
        action="store_true",
        help="give the calibration even if its unit was flagged or failed a limit",
    )
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from schemas.calibration_file import CalibrationFileError, qa_of, read_calibration_document
    from schemas.results_store import (
        CalibrationNotFound,
        calibration_times,
        find_calibration,
        iso,
        parse_when,
    )

    try:
        at = parse_when(args.at) if args.at else None
    except ValueError:
        raise CliError(f"--at {args.at!r} is not an ISO 8601 date or date-time") from None
    if at is not None and args.mode == "before" and re.fullmatch(r"\s*\d{4}-\d{2}-\d{2}\s*", args.at):
        at = at + timedelta(days=1) - timedelta(microseconds=1)  # the whole day
    if args.list:
        for when, produced, path, source in calibration_times(args.results, args.unit):
            try:
                qa = qa_of(read_calibration_document(path))
            except CalibrationFileError:
                qa = None
            status = qa["status"] if qa else "not judged"
            print(f"{iso(when)} ({source})  produced {iso(produced)}  {status:<10}  {path}")
    try:
        path = find_calibration(args.results, args.unit, at, args.mode)
    except CalibrationNotFound as exc:
        raise CliError(str(exc)) from None
    try:
        qa = qa_of(read_calibration_document(path))
    except CalibrationFileError as exc:
        raise CliError(str(exc)) from None
    if qa is not None and qa["status"] != "pass":
        reasons = qa.get("reasons") or []
        head = (
            f"unit {args.unit}: calibration {path} has QA status {qa['status']!r} in lot "
            f"{qa.get('lot')} (judged {qa.get('judged_at')}): " + "; ".join(reasons)
        )
        if not args.allow_flagged:
            print(
                f"mimucal calibration: refused: {head}; pass --allow-flagged to use it anyway",
                file=sys.stderr,
            )
            return EXIT_FLAGGED
        print(f"mimucal calibration: warning: {head}", file=sys.stderr)
    elif qa is None:
        print(f"mimucal calibration: note: {path} has no QA status (not judged in a lot)", file=sys.stderr)
    print(path)
    return 0
