"""Write the lot and unit reports of a demo store to a directory, or compare two such
directories report by report and table by table.

    python tools/compare_reports.py write OUT STORE   # reports of the store STORE (a
                                                        # synthetic 12-unit one when it is new)
    python tools/compare_reports.py compare BEFORE AFTER

A refactoring of reports/ leaves every report byte-identical but for the footer's generation
time; when it does not, ``compare`` names the tables that differ and the section of the first
difference."""

from __future__ import annotations

import argparse
import difflib
import re
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))


def write(out: Path, store: Path) -> int:
    from reports.lot import render_lot_report
    from reports.store import StoreView
    from reports.unit import render_unit_report
    from tools.synthetic_store import build_synthetic_store

    out.mkdir(parents=True, exist_ok=True)
    if not (store / "sessions.parquet").exists() and not (store / "tables").exists():
        build_synthetic_store(store, n_units=12, n_reps=5, n_outliers=2, n_failed=1, seed=50)
    view = StoreView(store)
    n = 0
    for lot in view.lots():
        (out / f"lot-{lot}.html").write_text(render_lot_report(store, lot))
        n += 1
        units = sorted({u for u in (view.of("sessions", lot)["unit"].astype(str))})
        for unit in units[:3] + units[-1:]:
            (out / f"unit-{unit}.html").write_text(render_unit_report(store, unit))
            n += 1
    print(f"{n} reports written to {out}")
    return 0


GENERATED = re.compile(r"generated \d{4}-\d\d-\d\d \d\d:\d\d UTC")
TABLE = re.compile(r"<table\b.*?</table>", re.S)
SECTION = re.compile(r'<(?:section|details)[^>]*\bid="([^"]+)"')


def compare(before: Path, after: Path) -> int:
    names = sorted({p.name for p in before.glob("*.html")} | {p.name for p in after.glob("*.html")})
    bad = 0
    for name in names:
        a, b = before / name, after / name
        if not a.exists() or not b.exists():
            print(f"{name}: only in {'after' if not a.exists() else 'before'}")
            bad += 1
            continue
        # the footer's generation time is the one thing that changes between two writes
        ta, tb = (GENERATED.sub("generated <time>", p.read_text()) for p in (a, b))
        tables_a, tables_b = TABLE.findall(ta), TABLE.findall(tb)
        same_tables = sum(x == y for x, y in zip(tables_a, tables_b))
        if ta == tb:
            print(f"{name}: identical ({len(tables_a)} tables)")
            continue
        bad += 1
        print(f"{name}: DIFFERS; tables {same_tables}/{max(len(tables_a), len(tables_b))} identical")
        for i, (x, y) in enumerate(zip(tables_a, tables_b)):
            if x != y:
                print(f"  table {i} differs")
        at = (
            next(i for i, (x, y) in enumerate(zip(ta, tb)) if x != y)
            if ta[: len(tb)] != tb[: len(ta)]
            else min(len(ta), len(tb))
        )
        sec = SECTION.findall(ta[:at])
        print(f"  first difference at char {at}, inside {sec[-1] if sec else 'the header'}")
        diff = difflib.unified_diff(
            ta[at - 200 : at + 300].splitlines(), tb[at - 200 : at + 300].splitlines(), lineterm=""
        )
        print("\n".join(list(diff)[:20]))
    print("all identical" if not bad else f"{bad} report(s) differ")
    return 1 if bad else 0


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = ap.add_subparsers(dest="cmd", required=True)
    w = sub.add_parser("write")
    w.add_argument("out", type=Path)
    w.add_argument("store", type=Path)
    c = sub.add_parser("compare")
    c.add_argument("before", type=Path)
    c.add_argument("after", type=Path)
    args = ap.parse_args(argv)
    if args.cmd == "write":
        return write(args.out, args.store)
    return compare(args.before, args.after)


if __name__ == "__main__":
    raise SystemExit(main())
