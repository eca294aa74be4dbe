"""``mimucal repair --results DIR``: rebuild what can be rebuilt of a damaged results store,
and say what could not be.

What every run checks first (``ResultsStore.verify``) and what repair does about it:

- a damaged table file (truncated, overwritten, not Parquet): removed. The ``units`` rows of
  its lot are rebuilt from the calibration files (the newest of each unit is its current
  one); every other table's rows come from the sessions, so the fingerprints of the lot's
  sessions are cleared and the next ``mimucal nightly`` recalibrates the lot's units from
  the dataset (said in the output);
- a current calibration file that is missing: the unit points to its newest remaining
  calibration file, or is marked failed when none is left; its sessions' fingerprints are
  cleared so that the next run recalibrates it;
- a symbolic link under the results folder: not removed (it may point to data someone
  needs); named, with the fix;
- reports: rebuilt from the tables.

Exit code 0 when the store verifies after the repair, 2 when something could not be
repaired (listed)."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

from flows.cli import CliError

EPILOG = """examples:
  mimucal repair --results results
  mimucal repair --results results --no-reports"""


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "repair",
        help="rebuild the damaged parts of a results store",
        description=__doc__,
        epilog=EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("--results", required=True, metavar="DIR", help="results store directory")
    p.add_argument("--no-reports", action="store_true", help="do not rebuild the reports")
    p.add_argument("--wait", action="store_true", help="wait for a run holding the store")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from schemas.results_store import ResultsStore

    root = Path(args.results)
    if not root.is_dir():
        raise CliError(f"{root} is not a directory")
    store = ResultsStore(root)
    with store.lock(owner="repair", wait=args.wait):
        done, not_done = repair_store(store)
        if not args.no_reports and not store.symlinks():
            from flows import runtime

            runtime.ensure_environment(args.results)
            from flows.nightly import write_reports

            lots = sorted(set(store.table_lots("units")) | set(store.table_lots("summary")))
            if lots:
                written, problems = write_reports(root, lots)
                done.append(f"rebuilt {len(written)} report(s) from the tables")
                not_done.extend(f"report: {p}" for p in problems)
        left = store.verify()
    for line in done:
        print(f"repaired: {line}")
    for line in not_done + [p for p in left if p not in not_done]:
        print(f"not repaired: {line}", file=sys.stderr)
    if not done and not not_done and not left:
        print(f"{root}: nothing to repair")
    return 2 if left or not_done else 0


def repair_store(store) -> tuple[list[str], list[str]]:
    """Repair ``store`` (held locked by the caller); returns (what was done, what could
    not be done), one line each."""
    from schemas.results_store import TABLES, table_file_problem

    done: list[str] = []
    not_done: list[str] = []
    links = store.symlinks()
    for link in links:
        not_done.append(
            f"{link} is a symbolic link; replace it by a real file/directory or "
            f"remove it (not removed: it may point to data you need)"
        )
    if links:
        return done, not_done
    damaged_lots: set[str | None] = set()
    units_damaged: set[str | None] = set()
    for name in TABLES:
        files = [(None, store.legacy_path(name))] if store.legacy_path(name).exists() else []
        files += list(store.partitions(name).items())
        for lot, path in files:
            why = table_file_problem(path, name)
            if not why:
                continue
            if path.is_dir():  # a directory where the table file belongs
                store.move_damaged(path)
            else:
                path.unlink()
            if path == store.legacy_path(name):  # a format-1.0 table: every lot
                lots = set(store.table_lots("sessions")) | {None}
            else:
                lots = {lot}
            damaged_lots |= lots
            if name == "units":
                units_damaged |= lots
            done.append(f"removed damaged {path} ({why})")
    done += _move_damaged_files(store)
    for lot in sorted(units_damaged, key=lambda x: (x is None, x or "")):
        n = _rebuild_units_rows(store, lot)
        done.append(f"rebuilt the units rows of lot {lot or '(all)'} from {n} calibration file(s)")
    # current calibration files that are missing
    units = store.read("units") if store.has_table("units") else None
    redo: set[tuple[str, str]] = set()
    if units is not None and len(units):
        changed = False
        for i, r in units.iterrows():
            f = r.get("calibration_file")
            if not (isinstance(f, str) and f) or (store.root / f).is_file():
                continue
            files = store.calibration_files(str(r["unit"]))
            if files:
                units.at[i, "calibration_file"] = str(files[-1][1].relative_to(store.root))
                units.at[i, "state"] = "stale"
                units.at[i, "reason"] = (
                    f"calibration file {f} was missing; the newest remaining one is used until the next run"
                )
                done.append(
                    f"unit {r['lot']}/{r['unit']}: missing {f}; now points to "
                    f"{units.at[i, 'calibration_file']}"
                )
            else:
                units.at[i, "calibration_file"] = None
                units.at[i, "state"] = "failed"
                units.at[i, "reason"] = f"calibration file {f} is missing and no other is left"
                not_done.append(
                    f"unit {r['lot']}/{r['unit']}: {f} is missing and no other "
                    f"calibration is left; the next 'mimucal nightly' "
                    f"recalibrates it"
                )
            redo.add((str(r["lot"]), str(r["unit"])))
            changed = True
        if changed:
            store.write("units", units)
    # what only the sessions can give back: recalibrated by the next nightly run
    if damaged_lots or redo:
        sessions = store.read("sessions")
        if len(sessions):
            lot_col = sessions["lot"].astype(object)
            hit = lot_col.isin([x for x in damaged_lots if x is not None]).to_numpy(dtype=bool, copy=True)
            if None in damaged_lots:
                hit |= lot_col.isna().to_numpy(dtype=bool)
            keys = list(zip(lot_col.astype(str), sessions["unit"].astype(str)))
            hit |= np.array([k in redo for k in keys], dtype=bool)
            if hit.any():
                sessions.loc[hit, "fingerprint"] = None
                store.write("sessions", sessions)
        for lot in sorted(x for x in damaged_lots if x is not None):
            not_done.append(
                f"lot {lot}: parameters, summary, residuals and the other per-"
                f"session rows cannot be rebuilt without the sessions; the next "
                f"'mimucal nightly' recalibrates the lot's units from the dataset"
            )
    return done, not_done


def _move_damaged_files(store) -> list[str]:
    """Calibration files that are not the store's (random bytes, a directory where a file
    belongs), a damaged ``store.json`` and a QA configuration that cannot be used: moved to
    ``damaged/`` (kept, out of every run's way). A unit whose current file was moved points to
    its newest remaining good file (the missing-file repair below); ``store.json`` is written
    again; without the QA configuration runs use the defaults until ``--config`` sets one."""
    from schemas.results_store import STORE_FORMAT_VERSION, calibration_file_problem, write_json_atomic

    done = []
    if store.calibrations_dir.is_dir():
        for d in sorted(store.calibrations_dir.iterdir()):
            if not d.is_dir():
                continue
            for p in sorted(d.glob("*.json")):
                why = calibration_file_problem(p)
                if why:
                    dest = store.move_damaged(p)
                    done.append(f"moved calibration file {p} ({why}) to {dest}")
    problems = store.config_file_problems()
    fp, qp = store.format_path, store.qa_config_path
    if any(p.startswith(str(fp)) for p in problems):
        dest = store.move_damaged(fp)
        write_json_atomic(
            fp, {"format_version": STORE_FORMAT_VERSION, "layout": "tables/<name>/lot=<lot>.parquet"}
        )
        done.append(f"moved damaged {fp} to {dest}; wrote it again (format {STORE_FORMAT_VERSION})")
    if any(str(qp) in p for p in problems):
        dest = store.move_damaged(qp)
        done.append(
            f"moved the QA configuration {qp}, which cannot be used, to {dest}; runs use the default "
            "configuration until --config sets one"
        )
    return done


def _rebuild_units_rows(store, lot: str | None) -> int:
    """The units rows of ``lot`` from the calibration files: each unit's newest file (its
    provenance names the lot, unit and run)."""
    import pandas as pd

    from schemas.store_rows import unit_row_from_calibration_file

    rows = []
    n = 0
    if store.calibrations_dir.is_dir():
        for d in sorted(store.calibrations_dir.iterdir()):
            files = store.calibration_files(d.name)
            if not files:
                continue
            ts, path = files[-1]
            try:
                prov = json.loads(path.read_text()).get("provenance") or {}
            except (OSError, ValueError):
                continue
            if lot is not None and prov.get("lot") != lot:
                continue
            n += 1
            rows.append(unit_row_from_calibration_file(d.name, prov, str(path.relative_to(store.root)), ts))
    df = pd.DataFrame(rows)
    if lot is None:
        store.write("units", df)
    else:
        store.write("units", df, lots=[lot])
    return n
