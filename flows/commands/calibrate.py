"""`mimucal calibrate DATASET --unit UNIT [--json FILE] [--full]`: one unit, every session, now.

Calibrates every session (repetition) of the unit as the nightly run does (xu2016 and
zhang2017 fits, model discovery unless --no-discovery, the average over repetitions) and
prints a short summary: the unit, repetitions calibrated and failed, the key parameters with
their spread over repetitions. --json FILE writes the unit's calibration file, the format the
results store holds and 'mimucal apply' reads (format "mimucal-calibration" with its
format_version; per-repetition fits under "repetitions"). --full prints that whole file."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from flows.cli import CliError

EPILOG = """examples:
  mimucal calibrate data/fleet --unit U0001
  mimucal calibrate data/fleet --unit U0001 --json U0001.json
  mimucal apply U0001.json data/fleet/lot=L1/unit=U0001/rep=1/samples.parquet out.parquet
  mimucal calibrate data/fleet --unit U0001 --full | less"""

# key parameters of the summary: (model, label, parameter names)
SUMMARY_ROWS = (
    ("gyro", "gyro scale k_g11 k_g22 k_g33", ("k_g11", "k_g22", "k_g33")),
    ("gyro", "gyro bias w0 x y z", ("w0_x", "w0_y", "w0_z")),
    ("accel", "accel scale k_a11 k_a22 k_a33", ("k_a11", "k_a22", "k_a33")),
    ("accel", "accel bias f0 x y z", ("f0_x", "f0_y", "f0_z")),
)


def register(sub) -> None:
    p = sub.add_parser(
        "calibrate",
        help="calibrate every session of one unit (xu2016 + zhang2017 fits)",
        description=__doc__,
        epilog=EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("dataset", type=Path, help="dataset root (lot=*/unit=*/rep=*/)")
    p.add_argument("--unit", required=True, help="unit id")
    p.add_argument(
        "--json",
        type=Path,
        default=None,
        metavar="FILE",
        help="write the unit's calibration file here (the format 'apply' reads)",
    )
    p.add_argument(
        "--full",
        "--verbose",
        dest="full",
        action="store_true",
        help="print the whole calibration file (JSON) instead of the summary",
    )
    p.add_argument("--no-discovery", action="store_true", help="skip model discovery")
    p.set_defaults(func=run)


def summary_lines(ur, failed: list[dict], n_reps: int) -> list[str]:
    """The short summary: unit, repetitions, model, key parameters (mean and spread over the
    repetitions, in the units of schemas.display)."""
    import numpy as np

    from schemas.display import spread_text, value_text
    from schemas.protocol_notes import notes_of

    out = ur.outcome
    lines = [f"unit {ur.unit} (lot {ur.lot}): {n_reps} repetition(s) calibrated, {len(failed)} failed"]
    terms = [t.name for t in out.applied.terms]
    lines.append(
        "model: w = K_g G + w0, f = K_a A + f0; extension terms: " + (", ".join(terms) if terms else "none")
    )
    by_key = {(s.model, s.name): s for s in out.calibration.summary}
    for model, label, names in SUMMARY_ROWS:
        ps = [by_key.get((model, n)) for n in names]
        if not all(ps):
            continue
        row_std = float(np.nanmedian([p.std for p in ps]))  # one number of decimals per row
        values = "  ".join(value_text(p.mean, p.unit, row_std) for p in ps)
        spreads = "  ".join(spread_text(p.std, p.unit) for p in ps)
        lines.append(f"{label:<30} {values}   (spread {spreads})")
    arms = [s for s in out.calibration.summary if s.model == "lever_arm"]
    if arms:
        worst = max(arms, key=lambda s: abs(s.std) if s.std == s.std else -1)
        lines.append(
            f"{'lever arms':<30} {len(arms)} components, largest spread "
            f"{spread_text(worst.std, worst.unit)} ({worst.name})"
        )
    if ur.diagnosis is not None:
        effects = [e.get("name") or e.get("effect") for e in (ur.diagnosis.get("effects") or [])]
        lines.append(
            "model discovery: "
            + (", ".join(map(str, effects)) if effects else "no effect beyond the base model")
            + ("; misfit left unexplained" if ur.diagnosis.get("unexplained") else "")
        )
    elif ur.discovery_note:
        lines.append(ur.discovery_note)
    for s in out.sessions:  # what was left out of a used session, or went wrong in its numbers
        lines += [f"warning rep {s.key.rep}: {w}" for w in s.warnings if s.succeeded]
    # what the protocol cannot observe: once, not as each repetition's warning
    for n in notes_of((ur.unit, s.protocol_notes) for s in out.sessions if s.succeeded):
        lines.append(f"protocol: {n.text} ({n.sessions} repetition(s))")
    for f in failed:
        msg = f["message"] or ""
        lines.append(f"failed rep {f['rep']}: " + (msg if msg.startswith("[") else f"[{f['code']}] {msg}"))
    return lines


def run(args) -> int:
    from flows.runtime import code_version
    from flows.unit_pipeline import UnitJob, calibrate_unit_job
    from schemas.calibration_file import calibration_to_dict, dumps_json, save_calibration
    from schemas.dataset import find_sessions
    from schemas.results_store import iso, utc_now
    from schemas.store_rows import calibration_file_extra

    if not args.dataset.is_dir():
        raise CliError(f"dataset {args.dataset} is not a directory")
    refs, errors = find_sessions(args.dataset, unit=args.unit)
    for e in errors:
        print(f"skipped: {e}", file=sys.stderr)
    if not refs:
        from flows.user_errors import units_under

        raise CliError(
            f"no session of unit {args.unit!r} under {args.dataset} (units: {units_under(args.dataset)})"
        )
    lot = refs[0].key.lot
    ur = calibrate_unit_job(
        UnitJob(lot, args.unit, refs, "mimucal calibrate"), run_discovery=not args.no_discovery
    )
    out = ur.outcome
    failed = [
        {"rep": s.key.rep, "code": s.code, "message": s.message} for s in out.sessions if not s.succeeded
    ]
    if not ur.calibrated:
        for f in failed:
            print(f"failed: {f['message']}", file=sys.stderr)
        raise CliError(f"unit {args.unit}: every session failed; no calibration")
    n_reps = len(out.calibration.reps)
    extra = calibration_file_extra(
        ur,
        {
            "run_id": None,
            "command": "mimucal calibrate",
            "dataset": str(args.dataset),
            "code_version": code_version(),
            "calibrated_at": iso(utc_now()),
        },
    )
    if args.json:
        save_calibration(out.applied, args.json, extra, extra_nonfinite="null", default=str)
    if args.full:
        sys.stdout.write(
            dumps_json(calibration_to_dict(out.applied, extra), default=str, null_keys=frozenset(extra))
        )
    else:
        for line in summary_lines(ur, failed, n_reps):
            print(line)
        if args.json:
            print(f"calibration file: {args.json} (mimucal apply reads it; --full prints it)")
    return 0 if not failed else 1
