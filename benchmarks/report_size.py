"""Size and render time of a lot report: builds a synthetic results store of N units
(default 50, 5 repetitions, 2 outliers, 1 failed session), writes the lot report, the unit
report of one unit and the fleet index, and times them in Debian's headless Chromium.

    .venv/bin/python benchmarks/report_size.py            # 50 units
    .venv/bin/python benchmarks/report_size.py --units 12
    .venv/bin/python benchmarks/report_size.py --no-browser --repeat 3   # writing only

Prints one Markdown table row per report (the header with --header). "write" is the wall and
the CPU time (``time.process_time``, the figure to compare on a shared machine) of writing the
report from a fresh read of the store, the smallest of ``--repeat`` runs.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from reports.browser import Chromium, find_chromium  # noqa: E402
from reports.index import write_fleet_index  # noqa: E402
from reports.lot import write_lot_report  # noqa: E402
from reports.unit import write_unit_report  # noqa: E402
from tools.synthetic_store import build_synthetic_store  # noqa: E402

HEADER = (
    "| report | units | file size [MB] | write [s] | write CPU [s] | open, first time [s] | open again [s] "
    "| all units opened, every figure drawn [s] | figures |\n|---|---|---|---|---|---|---|---|---|"
)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--units", type=int, default=50)
    ap.add_argument("--reps", type=int, default=5)
    ap.add_argument("--header", action="store_true", help="print the Markdown table header")
    ap.add_argument("--keep", type=Path, help="build the store here instead of a temp dir")
    ap.add_argument("--repeat", type=int, default=1, help="write each report N times, keep the fastest")
    ap.add_argument("--no-browser", action="store_true", help="do not open the reports in Chromium")
    args = ap.parse_args(argv)
    tmp = None
    root = args.keep
    if root is None:
        tmp = tempfile.TemporaryDirectory(prefix="mimucal-report-bench-")
        root = Path(tmp.name)
    t0 = time.perf_counter()
    truth = build_synthetic_store(
        root, n_units=args.units, n_reps=args.reps, n_outliers=2, n_failed=1, seed=50, nav_samples=60_000
    )
    t_store = time.perf_counter() - t0
    rows = []
    for kind, write in (
        ("lot", lambda: write_lot_report(root, truth.lot)),
        ("unit", lambda: write_unit_report(root, truth.units[0])),
        ("fleet index", lambda: write_fleet_index(root)),
    ):
        t_write = t_cpu = float("inf")
        for _ in range(max(1, args.repeat)):
            t0, c0 = time.perf_counter(), time.process_time()
            path = write()
            t_write = min(t_write, time.perf_counter() - t0)
            t_cpu = min(t_cpu, time.process_time() - c0)
        rows.append([kind, path, path.stat().st_size / 1e6, t_write, t_cpu])
    if args.header:
        print(HEADER)
    chromium = None if args.no_browser else find_chromium()
    if chromium is None and not args.no_browser:
        print("chromium not found: render times not measured", file=sys.stderr)
    for kind, path, size_mb, t_write, t_cpu in rows:
        cold = warm = every = float("nan")
        n = ""
        if chromium:
            with Chromium(timeout_s=600) as b:  # a fresh browser per report: a cold first open
                cold = b.open(path) + b.wait_figures(300)
                warm = b.open(path) + b.wait_figures(300)  # V8 has cached plotly.js by now
                t0 = time.perf_counter()
                b.evaluate("mimucalExpandAll(true)")
                b.wait_figures(600)
                every = warm + time.perf_counter() - t0
                n = b.evaluate("document.body.getAttribute('data-figures-rendered')")
                if b.log.errors:
                    print(f"{kind}: JavaScript errors: {b.log.errors}", file=sys.stderr)
        print(
            f"| {kind} | {args.units} | {size_mb:.2f} | {t_write:.2f} | {t_cpu:.2f} "
            f"| {cold:.2f} | {warm:.2f} "
            f"| {every:.2f} | {n} |",
            flush=True,
        )
    print(
        f"(synthetic store of {args.units} units x {args.reps} reps built in {t_store:.1f} s; "
        f"navigation traces 60,000 samples per case, downsampled in the unit report)",
        file=sys.stderr,
    )
    if tmp:
        tmp.cleanup()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
