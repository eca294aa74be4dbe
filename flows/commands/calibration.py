"""``mimucal calibration --results DIR --unit U [--at ISO]``: the calibration file valid for a
unit at a date (as imucal's ``find_closest_calibration_info_to_date``).

Default: the latest calibration produced at or before ``--at`` (default now, UTC);
``--mode after`` the earliest at or after, ``--mode closest`` the nearest."""
from __future__ import annotations

import argparse

from flows.cli import CliError

EPILOG = """examples:
  mimucal calibration --results results --unit U0001
  mimucal calibration --results results --unit U0001 --at 2026-11-20T12:00:00Z
  mimucal calibration --results results --unit U0001 --at 2026-11-20 --mode closest --list"""


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("calibration", help="find the calibration file valid for a unit at a date",
                       description=__doc__, epilog=EPILOG,
                       formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--results", required=True, metavar="DIR", help="results store directory")
    p.add_argument("--unit", required=True, help="unit id")
    p.add_argument("--at", default=None, metavar="ISO",
                   help="ISO 8601 date or date-time (UTC if no offset); default now")
    p.add_argument("--mode", choices=("before", "after", "closest"), default="before")
    p.add_argument("--list", action="store_true", help="also list every calibration of the unit")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from schemas.results_store import CalibrationNotFound, ResultsStore, find_calibration, iso, parse_when
    try:
        at = parse_when(args.at) if args.at else None
    except ValueError:
        raise CliError(f"--at {args.at!r} is not an ISO 8601 date or date-time") from None
    if args.list:
        for ts, path in ResultsStore(args.results).calibration_files(args.unit):
            print(f"{iso(ts)}  {path}")
    try:
        print(find_calibration(args.results, args.unit, at, args.mode))
    except CalibrationNotFound as exc:
        raise CliError(str(exc)) from None
    return 0
