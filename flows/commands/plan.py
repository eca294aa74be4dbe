"""`mimucal plan STEPS(.parquet|.csv) [--latitude DEG --table-heading DEG]`: what a protocol
can and cannot identify, before anyone runs the turntable.

Every catalogue term's columns on the steps (nominal unit and noise, a nominal warm-up) are
analysed with the affine calibration projected out (:mod:`calib_core.discovery.plan`): which terms are
determined, which parameters are not, which terms are confounded, and which step sets of the
library would separate them; then the smallest size of each parameter that discovery finds
on these steps with ``--reps`` repetitions of a MEMS unit's noise, and the share of each
effect's realistic sizes (0.25x, 0.5x, 1x) it would name
(:mod:`calib_core.discovery.detection`). See docs/model-discovery.md, "Identifiability" and
"Detection limits".
"""

from __future__ import annotations

from pathlib import Path

from flows.cli import CliError


def register(sub) -> None:
    p = sub.add_parser(
        "plan",
        help="what a protocol (steps table) can and cannot identify",
        description="Analyse a steps table (the contract's steps.parquet, or the same "
        "columns as CSV) before acquisition: which catalogue effects its steps "
        "determine, which are confounded or undetermined, and which step sets "
        "would separate them.",
    )
    p.add_argument("steps", type=Path, metavar="STEPS", help="steps.parquet or .csv")
    p.add_argument(
        "--latitude",
        type=float,
        default=None,
        metavar="DEG",
        help="latitude of the table (with --table-heading: the Earth rate's direction is known)",
    )
    p.add_argument(
        "--table-heading",
        type=float,
        default=None,
        metavar="DEG",
        help="heading of the table's zero reference, degrees east of true north",
    )
    p.add_argument(
        "--tol",
        type=float,
        default=0.05,
        help="confounded / undetermined below this sine of angle (default 0.05)",
    )
    p.add_argument(
        "--reps",
        type=int,
        default=5,
        metavar="N",
        help="repetitions per unit for the detection limits (default 5, the production protocol)",
    )
    p.set_defaults(func=run)


def read_steps_table(path: Path):
    """The steps table, validated as the reader validates steps.parquet."""
    import pandas as pd
    import pyarrow as pa

    from schemas.errors import SessionError
    from schemas.reader import validate_steps

    if not path.is_file():
        raise CliError(f"steps table {path} does not exist")
    try:
        if path.suffix.lower() == ".csv":
            table = pa.Table.from_pandas(pd.read_csv(path), preserve_index=False)
            table = table.set_column(
                table.schema.get_field_index("step"), "step", table.column("step").cast(pa.int32())
            )
        else:
            import pyarrow.parquet as pq

            table = pq.read_table(path)
    except (OSError, ValueError, KeyError, pa.ArrowException) as exc:
        raise CliError(f"{path}: cannot read the steps table ({exc})") from None
    try:
        return validate_steps(table, str(path), path.name)
    except SessionError as exc:
        raise CliError(str(exc)) from None


def run(args) -> int:
    from calib_core.discovery.detection import detection_limits
    from calib_core.discovery.plan import plan

    if not 0 < args.tol < 1:
        raise CliError(f"--tol must be between 0 and 1, got {args.tol}")
    if args.reps < 2:
        raise CliError(f"--reps must be at least 2 (the noise is the repetitions' scatter), got {args.reps}")
    steps = read_steps_table(args.steps)
    result = plan(steps, tol=args.tol, latitude_deg=args.latitude, table_heading_deg=args.table_heading)
    limits = detection_limits(
        steps, n_reps=args.reps, latitude_deg=args.latitude, table_heading_deg=args.table_heading
    )
    print("\n".join(result.lines() + limits.lines() + limits.coverage_lines()))
    return 0
