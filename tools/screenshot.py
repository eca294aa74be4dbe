"""Screenshot of a lot report for the documentation (docs/img/lot-report.png).

    .venv/bin/python -m tools.screenshot RESULTS LOT OUT.png [--height 1750]
    .venv/bin/python -m tools.screenshot --synthetic OUT.png   # 12-unit synthetic lot

Writes the lot report if needed, opens it in headless Chromium, opens the first flagged
unit's section below the lot overview and captures the top of the page.
"""

from __future__ import annotations

import argparse
import tempfile
from pathlib import Path

from reports.browser import Chromium
from reports.lot import write_lot_report
from tools.synthetic_store import build_synthetic_store


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("args", nargs="+", help="RESULTS LOT OUT.png, or OUT.png with --synthetic")
    ap.add_argument("--synthetic", action="store_true")
    ap.add_argument("--width", type=int, default=1400)
    ap.add_argument("--height", type=int, default=1750)
    a = ap.parse_args(argv)
    tmp = None
    if a.synthetic:
        tmp = tempfile.TemporaryDirectory()
        truth = build_synthetic_store(tmp.name, n_units=12, n_outliers=2, n_failed=1, seed=20261121)
        root, lot, out = Path(tmp.name), truth.lot, Path(a.args[0])
    else:
        root, lot, out = Path(a.args[0]), a.args[1], Path(a.args[2])
    path = write_lot_report(root, lot)
    with Chromium(width=a.width, height=a.height) as b:
        b.open(path)
        b.wait_figures()
        b.pump(0.3)
        if b.log.errors:
            raise SystemExit(f"JavaScript errors: {b.log.errors}")
        b.screenshot(out, full_page=True, max_height=a.height)
    print(out)
    if tmp:
        tmp.cleanup()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
