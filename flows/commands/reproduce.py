"""`mimucal reproduce PAPER`: simulate a paper's unit, run its method, compare with its tables."""

from __future__ import annotations

import importlib
from pathlib import Path

from flows.cli import CliError

PAPERS = {
    "xu2016": "calib_core.paper.xu2016",
    "zhang2017": "calib_core.paper.zhang2017",
}


def register(sub) -> None:
    p = sub.add_parser(
        "reproduce",
        help="reproduce a seed paper's tables by simulation",
        description="Simulate the unit of a seed paper with its published values as truth, run "
        "the paper's method on every repetition and print the published and the "
        "reproduced tables side by side, with what cannot be matched.",
    )
    p.add_argument("paper", choices=sorted(PAPERS), help="which paper")
    p.add_argument("--rate", type=float, default=100.0, help="sample rate, Hz (default 100)")
    p.add_argument("--reps", type=int, default=5, help="repetitions (default 5, as the papers)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument(
        "--fast",
        action="store_true",
        help="draw step means directly instead of simulating and averaging samples",
    )
    p.add_argument("--json", type=Path, default=None, help="also write the tables as JSON")
    p.set_defaults(func=run)


def run(args) -> int:
    if args.rate <= 0 or args.reps < 2:
        raise CliError("--rate must be > 0 and --reps >= 2")
    module = importlib.import_module(PAPERS[args.paper])
    kwargs = dict(rate_hz=args.rate, reps=args.reps, seed=args.seed)
    if args.paper == "xu2016" and not args.fast:
        from schemas.averaging import step_means_from_tables

        def averager(key, steps, samples, metadata):
            import pyarrow as pa

            return step_means_from_tables(
                key, steps, pa.Table.from_pandas(samples, preserve_index=False), metadata
            )[0]

        kwargs["averager"] = averager
    report = module.reproduce(**kwargs)
    print(report.text)
    if args.json:
        from schemas.calibration_file import write_json_atomic

        write_json_atomic(args.json, report.to_dict())
    return 0
