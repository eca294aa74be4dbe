"""``mimucal report --results DIR --lot LOT``: rebuild a lot's flags and report from the
results store (no raw data is read)."""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

from flows.cli import CliError

EPILOG = """examples:
  mimucal report --results results --lot L01
  mimucal report --results results --lot L01 --config limits.toml"""


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("report", help="rebuild one lot's outlier flags and HTML report",
                       description=__doc__, epilog=EPILOG,
                       formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--results", required=True, metavar="DIR", help="results store directory")
    p.add_argument("--lot", required=True, help="lot id")
    p.add_argument("--config", metavar="TOML", default=None,
                   help="outlier options and per-parameter limits")
    p.add_argument("--wait", action="store_true", help="wait for a run holding the store")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from schemas.results_store import ResultsStore
    store = ResultsStore(Path(args.results))
    if not store.has_table("summary") and not store.has_table("sessions"):
        raise CliError(f"{args.results} is not a results store (no sessions table); run "
                       f"'mimucal nightly' first")
    from flows import runtime
    runtime.ensure_environment(args.results)
    from calib_core.outliers import OutlierConfigError
    from flows import nightly
    from schemas.results_store import StoreLockedError
    try:
        out = nightly.lot_quality_report(args.results, args.lot, args.config, args.wait)
    except (StoreLockedError, OutlierConfigError, FileNotFoundError, LookupError) as exc:
        raise CliError(str(exc)) from None
    for lf in out["flags"]:
        print(lf["note"])
        for f in lf["flags"]:
            print(f"flag {f['lot']}/{f['unit']}: [{f['kind']}] {f['reason']}")
    for p in out["problems"]:
        print(f"report: {p}", file=sys.stderr)
    for r in out["reports"]:
        print(r)
    return 1 if out["problems"] else 0
