"""`mimucal calibrate DATASET --unit UNIT [--json FILE]`: one unit, every session, now."""
from __future__ import annotations

import json
import sys
from pathlib import Path

from flows.cli import CliError


def register(sub) -> None:
    p = sub.add_parser(
        "calibrate", help="calibrate every session of one unit (xu2016 + zhang2017 fits)",
        description="Calibrate every session (repetition) of one unit from a hive-partitioned "
                    "dataset and print or write the calibration per repetition and its "
                    "mean/std across repetitions.")
    p.add_argument("dataset", type=Path, help="dataset root (lot=*/unit=*/rep=*/)")
    p.add_argument("--unit", required=True, help="unit id")
    p.add_argument("--json", type=Path, default=None, metavar="FILE",
                   help="write the calibration document here (default: print it)")
    p.set_defaults(func=run)


def run(args) -> int:
    from flows.unit_pipeline import calibrate_unit
    from schemas.calibration_file import write_json_atomic
    from schemas.dataset import find_sessions
    from schemas.unit_document import unit_document

    if not args.dataset.is_dir():
        raise CliError(f"dataset {args.dataset} is not a directory")
    refs, errors = find_sessions(args.dataset, unit=args.unit)
    for e in errors:
        print(f"skipped: {e}", file=sys.stderr)
    if not refs:
        raise CliError(f"no session of unit {args.unit!r} under {args.dataset}")
    outcome = calibrate_unit(refs, keep_step_means=False)
    failed = [{"rep": s.key.rep, "code": s.code, "message": s.message}
              for s in outcome.sessions if not s.succeeded]
    for f in failed:
        print(f"failed: {f['message']}", file=sys.stderr)
    reps = [s.calibration for s in outcome.sessions if s.succeeded and s.calibration]
    if not reps:
        raise CliError(f"unit {args.unit}: every session failed; no calibration")
    doc = unit_document(outcome.lot, outcome.unit, reps, failed)
    if args.json:
        write_json_atomic(args.json, doc)
        print(f"unit {outcome.unit} (lot {outcome.lot}): {len(reps)} repetition(s) calibrated, "
              f"{len(failed)} failed -> {args.json}")
    else:
        json.dump(doc, sys.stdout, indent=2)
        print()
    return 0 if not failed else 1
