"""The outlier flags in the results store: re-flag the lots a run touched, write the flags
to the ``summary`` and ``units`` tables and each unit's QA status into its calibration file,
and keep the flag state between runs so that a rerun re-flags only what can have changed.

The rules are :mod:`calib_core.outliers` (robust z against the lot or, for small lots, the
fleet history; repetition spread; acceptance limits); the decisions that need no file
(which lots changed, which units are flagged, a unit's QA block) are
:mod:`calib_core.flag_decisions`. This module reads and writes the store around them.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np
import pandas as pd

from calib_core.flag_decisions import (
    acquisition_seconds,
    flagged_units,
    has_small_lots,
    lots_to_reflag,
    lots_with_new_flags,
    pooled_doc,
    qa_status,
    units_with_flags,
)
from calib_core.outliers import (
    LotFlags,
    OutlierConfig,
    ThresholdTable,
    apply_flags,
    flag_lots,
    pooled_scales,
    pooling_rows,
)
from schemas.results_store import ResultsStore, iso, utc_now


def reflag_after_update(
    store: ResultsStore, touched: list[str], config: OutlierConfig
) -> tuple[list[LotFlags], list[str]]:
    """Leave every lot's flags as a re-flag of every lot would (the robust scale is pooled
    over all lots, so one lot's new values can move every lot's scores); return the flags of
    the touched lots and the lots whose reports must be rebuilt: the touched ones and any
    whose flagged units changed. Only the lots that can have changed are re-flagged
    (:func:`_reflag_fleet`)."""
    if not touched:
        return [], []
    all_lots = sorted(set(store.table_lots("summary")) | set(touched))
    lf, before, after = _reflag_fleet(store, touched, config)
    changed = {lot for lot in all_lots if before.get(lot, set()) != after.get(lot, set())}
    return [x for x in lf if x.lot in set(touched)], sorted(set(touched) | changed)


def reflag_lots(store: ResultsStore, lots: set[str] | list[str], config: OutlierConfig) -> list[LotFlags]:
    """Recompute the flags of the given lots from the whole summary (the robust scale is
    pooled over all lots: the summary is small, ~100 rows per unit, and read whole) and write
    them to the summary and units tables, rewriting only the lots whose rows changed."""
    return _reflag(store, lots, config)[0]


def _reflag(
    store: ResultsStore, lots: set[str] | list[str], config: OutlierConfig, keep_state: bool = False
) -> tuple[list[LotFlags], dict[str, set[str]], dict[str, set[str]]]:
    """reflag_lots, plus each lot's flagged units before and after (from the units table it
    reads and writes anyway). ``keep_state``: ``lots`` are all the lots, and the flag state
    (:func:`_reflag_fleet`) is written for the next run."""
    summary = store.read("summary")
    if not len(summary) or not lots:
        return [], {}, {}
    present = set(summary["lot"].dropna().astype(str))
    todo = sorted(set(map(str, lots)) & present)
    if not todo:
        return [], {}, {}
    lf = _flag(store, summary, config, todo)
    before, after = _write_flags(store, summary, lf, todo, lots=None, config=config)
    if keep_state:
        _write_flag_state(store, config, pooling_rows(summary, config), pooled_scales(summary, config))
    return lf, before, after


def unit_times(store: ResultsStore) -> dict[tuple[str, str], float]:
    """(lot, unit) -> acquisition time of its current calibration (POSIX s), from the units
    table (:func:`calib_core.flag_decisions.acquisition_seconds`)."""
    return acquisition_seconds(store.read("units"))


def _has_small_lots(store: ResultsStore, config: OutlierConfig) -> bool:
    """Whether any lot is judged against the fleet history (config.history_below)."""
    if not config.uses_history():
        return False
    return has_small_lots(store.read("units", columns=["lot", "unit"]), config)


def _flag(
    store: ResultsStore, summary: pd.DataFrame, config: OutlierConfig, todo: list[str]
) -> list[LotFlags]:
    """flag_lots of ``todo``, with the run's threshold table made from the thresholds
    simulated by earlier runs (kept in the store; new lot layouts are added to it) and the
    units' acquisition times (small lots' fleet history)."""
    cached = store.read_outlier_thresholds()
    thresholds = ThresholdTable(cached)
    times = unit_times(store) if config.uses_history() else None
    lf = flag_lots(summary.astype({"lot": object, "unit": object}), config, todo, times, thresholds)
    now = thresholds.document()
    if now != cached:  # new lot layouts simulated: keep them for the next process
        store.write_outlier_thresholds(now)
    return lf


def _write_flags(
    store: ResultsStore,
    summary: pd.DataFrame,
    lf: list[LotFlags],
    todo: list[str],
    lots: list[str] | None,
    config: OutlierConfig,
) -> tuple[dict[str, set[str]], dict[str, set[str]]]:
    """Write the flags ``lf`` of the lots ``todo`` to the summary and units tables:
    ``summary`` holds the stored rows of ``lots`` (None: every lot), and the units rows of
    those lots are read, the flags of those not in ``todo`` normalised (missing: not
    flagged). Only lots whose rows changed are rewritten. Returns each lot's flagged units
    before and after."""
    flagged_summary = apply_flags(summary, lf)
    # rows of lots whose flags changed are rewritten, the other lots' files left alone
    changed = lots_with_new_flags(summary, flagged_summary)
    if changed is None:
        store.write("summary", flagged_summary, lots=lots, skip_unchanged=True, previous=summary)
    elif changed:
        in_changed = flagged_summary["lot"].astype(object).isin(changed).to_numpy()
        store.write("summary", flagged_summary[in_changed], lots=changed)
    units_before = store.read("units", lots=lots)
    units = units_before
    if len(units):
        units = units_with_flags(units, lf, todo)
        store.write("units", units, lots=lots, skip_unchanged=True, previous=units_before)
        stamp_qa(store, units_before, units, lf, config, flagged_summary)
    return flagged_units(units_before), flagged_units(units)


def stamp_qa(
    store: ResultsStore,
    before: pd.DataFrame,
    after: pd.DataFrame,
    lot_flags: list[LotFlags],
    config: OutlierConfig,
    summary: pd.DataFrame | None = None,
) -> list[str]:
    """Write the QA status into the current calibration file of every unit of the lots
    re-flagged (``lot_flags``) whose status is new: freshly calibrated (no flags yet), or
    whose flags changed. Each file is rewritten atomically and keeps its earlier statuses
    (``qa_history``); the lot's context goes to ``qa/<lot>.json``, with the spread and
    outliers of its thermal coefficients (``thermal_spread``, from the flagged ``summary``
    rows; lots calibrated over temperature only). Returns the files rewritten."""
    from calib_core.models.thermal import lot_spread_records
    from schemas.calibration_file import CalibrationFileError, set_qa_status

    when = iso(utc_now())
    by_lot = {x.lot: x for x in lot_flags}
    prev = (
        {(str(r.lot), str(r.unit)): (r.flagged, r.flag_reason) for r in before.itertuples()}
        if len(before)
        else {}
    )
    done = []
    for lf in lot_flags:
        doc = {
            "lot": lf.lot,
            "n_units": lf.n_units,
            "reference": lf.reference,
            "reference_detail": lf.reference_detail,
            "z_threshold": lf.z_threshold_used,
            "note": lf.note,
            "judged_at": when,
        }
        if summary is not None and len(summary):
            thermal = lot_spread_records(summary[summary["lot"].astype(str) == lf.lot])
            if thermal:
                doc["thermal_spread"] = thermal
        store.write_qa_lot(lf.lot, doc)
    for r in after.itertuples():
        lot, unit = str(r.lot), str(r.unit)
        lf = by_lot.get(lot)
        path = getattr(r, "calibration_file", None)
        if lf is None or not isinstance(path, str) or not path:
            continue
        old_flagged, old_reason = prev.get((lot, unit), (None, None))
        if (
            old_flagged is not None
            and not pd.isna(old_flagged)
            and bool(old_flagged) == bool(r.flagged)
            and old_reason == r.flag_reason
        ):
            continue  # judged before, same status
        try:
            set_qa_status(store.root / path, qa_status(lf, unit, config, when))
            done.append(path)
        except (OSError, CalibrationFileError) as exc:  # the flags stand; the file says less
            print(f"QA status of {lot}/{unit} not written to {path}: {exc}", file=sys.stderr)
    return done


# --- the flag state kept between runs --------------------------------------------------------------
# A lot's flags and scores depend on its own summary rows, the configuration, the flagging code
# and, through the pooled robust scales, on the other lots' means (calib_core.outliers.
# pooled_scales). cache/flag_state.parquet keeps, as the last re-flag left them: the pooled rows
# of every lot (pooling_rows: ~24 per unit), the pooled scales, the configuration and code they
# were computed with, and the (size, mtime, inode) of each lot's summary and units file. A lot
# whose files are unchanged since then still holds exactly the flags a re-flag would give it,
# as long as the pooled scales are the same: a re-flag after an update then re-flags only the
# touched lots and those whose files changed (reading only their files), and every lot when the
# pooled scales moved (any change of a scale changes every lot's scores). Exact, no tolerance:
# the stored scores are those of a re-flag of every lot.
FLAG_STATE_VERSION = 1


def _flag_state_key(config: OutlierConfig) -> str:
    """The configuration and flagging code the state was computed with (the source of
    calib_core.outliers: a new version of the rules makes the state stale)."""
    import dataclasses
    import hashlib

    import calib_core.outliers as outliers

    code = hashlib.sha256(Path(outliers.__file__).read_bytes()).hexdigest()[:16]
    return json.dumps(
        {"config": dataclasses.asdict(config), "outliers_source": code}, sort_keys=True, default=str
    )


def _lot_files(store: ResultsStore) -> dict[str, dict[str, list[int] | None]] | None:
    """(size, mtime_ns, inode) of each lot's summary and units files; None when a table is
    a format-1.0 flat file or has rows without a lot (the state is then not used)."""
    stats = {name: store.partition_stats(name) for name in ("summary", "units")}
    if any(st is None or None in st for st in stats.values()):
        return None
    lots = set(stats["summary"]) | set(stats["units"])
    return {
        lot: {name: (list(st[lot]) if lot in st else None) for name, st in stats.items()}
        for lot in sorted(lots)
    }


def _write_flag_state(store: ResultsStore, config: OutlierConfig, rows: pd.DataFrame, pooled: dict) -> None:
    """Record the state after a re-flag that left every lot as a re-flag of all would."""
    files = _lot_files(store)
    if files is None:
        return
    rows = rows.astype({"lot": str, "unit": str, "model": str, "parameter": str})
    store.write_flag_state(
        rows.sort_values("lot", kind="stable").reset_index(drop=True),
        {
            "version": FLAG_STATE_VERSION,
            "key": _flag_state_key(config),
            "pooled": pooled_doc(pooled),
            "files": files,
        },
    )


def _reflag_fleet(
    store: ResultsStore, touched: list[str], config: OutlierConfig
) -> tuple[list[LotFlags], dict[str, set[str]], dict[str, set[str]]]:
    """:func:`_reflag` of every lot, re-flagging only the touched lots and those whose files
    changed since the flag state was written, while the pooled scales are unchanged; every
    lot (and a new state) when there is no usable state or the scales moved. Returns the
    flags of the lots re-flagged (the touched ones among them) and the flagged units before
    and after of the lots whose units rows were read."""
    state = store.read_flag_state()
    files = _lot_files(store)
    # a small lot is judged against the history of earlier lots, which the pooled scales
    # do not summarise: every lot is re-flagged then
    if state is not None and files is not None and not _has_small_lots(store, config):
        rows, doc = state
        if doc.get("version") == FLAG_STATE_VERSION and doc.get("key") == _flag_state_key(config):
            done = _reflag_changed_lots(store, touched, config, rows, doc, files)
            if done is not None:
                return done
    all_lots = sorted(set(store.table_lots("summary")) | set(map(str, touched)))
    return _reflag(store, all_lots, config, keep_state=True)


def _reflag_changed_lots(
    store: ResultsStore, touched: list[str], config: OutlierConfig, rows: pd.DataFrame, doc: dict, files: dict
) -> tuple[list[LotFlags], dict[str, set[str]], dict[str, set[str]]] | None:
    """The partial re-flag of :func:`_reflag_fleet`; None when the pooled scales moved."""
    dirty, clean = lots_to_reflag(doc.get("files") or {}, files, touched)
    if not clean:  # every lot changed (a nightly run of the whole fleet): the full re-flag
        return None
    summary = store.read("summary", lots=dirty)
    kept = rows[rows["lot"].isin(clean).to_numpy()]
    pool = pd.concat(
        [pooling_rows(summary, config).astype({"lot": str, "unit": str}), kept], ignore_index=True
    )
    pooled = pooled_scales(pool, config)
    if pooled_doc(pooled) != doc.get("pooled"):
        return None
    present = set(summary["lot"].dropna().astype(str))
    todo = sorted(set(dirty) & present)
    lf = []
    if todo:
        # the clean lots' pooled rows stand in for their summary: flag_lots takes the pooled
        # scales from them and flags only the lots in todo
        lf = _flag(
            store,
            pd.concat([summary, kept.assign(std=np.nan, n_reps=np.nan)], ignore_index=True),
            config,
            todo,
        )
    before, after = _write_flags(store, summary, lf, todo, lots=dirty, config=config)
    _write_flag_state(store, config, pool, pooled)
    return lf, before, after
