"""Decisions of the re-flag that need no file: which lots changed since the flag state was
kept, which units a units table flags, the units rows with new flags, which lots are small
enough to be judged against the fleet history, each unit's acquisition time, and a unit's QA
block. :mod:`schemas.flagging` reads and writes the store around them; the flagging rules
themselves are :mod:`calib_core.outliers`.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import pandas as pd

from calib_core.outliers import KIND_LIMIT, LOT_COLUMNS, LotFlags, OutlierConfig


def flagged_units(units: pd.DataFrame) -> dict[str, set[str]]:
    """Lot -> its flagged units (every lot of the units table, possibly with none)."""
    out: dict[str, set[str]] = {}
    if len(units) and "flagged" in units:
        for r in units[["lot", "unit", "flagged"]].itertuples():
            out.setdefault(str(r.lot), set())
            if r.flagged is not None and not pd.isna(r.flagged) and bool(r.flagged):
                out[str(r.lot)].add(str(r.unit))
    return out


# the summary columns calib_core.outliers.apply_flags sets; it leaves every other one alone
FLAG_COLUMNS = ("flagged", "flag_reason", *LOT_COLUMNS)


def lots_with_new_flags(before: pd.DataFrame, after: pd.DataFrame) -> list[str] | None:
    """Lots whose summary rows differ between ``before`` and ``after = apply_flags(before)``
    (same rows, same order): only the flag columns can differ, compared exactly (NaN equal
    to NaN, a missing value unequal to any value), as the store's skip-unchanged comparison
    would decide, without its per-lot frame comparison (~0.2 s when a lot differs)."""
    differs = np.zeros(len(after), dtype=bool)
    for col in FLAG_COLUMNS:
        if col not in before:
            differs[:] = True
            break
        a, b = before[col], after[col]
        a_na, b_na = a.isna().to_numpy(), b.isna().to_numpy()
        both = ~a_na & ~b_na
        if col in LOT_COLUMNS:
            a_v, b_v = a.to_numpy(float, na_value=np.nan), b.to_numpy(float, na_value=np.nan)
            differs |= (a_na != b_na) | (both & (a_v != b_v))
        else:
            a_v, b_v = a.to_numpy(object), b.to_numpy(object)
            ne = np.zeros(len(a_v), dtype=bool)
            ne[both] = a_v[both] != b_v[both]
            differs |= (a_na != b_na) | ne
    lots = after["lot"].to_numpy(object, na_value=None)[differs]
    if any(x is None for x in lots):
        return None  # rows without a lot: let the store compare them (never seen)
    return sorted({str(x) for x in lots})


def units_with_flags(units: pd.DataFrame, lot_flags: list[LotFlags], todo: list[str]) -> pd.DataFrame:
    """``units`` (rows of the units table) with ``flagged`` and ``flag_reason`` set from
    ``lot_flags`` for the lots in ``todo`` (every reason, "[kind] reason", joined by "; "),
    and normalised for the others (missing: not flagged)."""
    units = units.copy()
    flagged: dict[tuple[str, str], list[str]] = {}
    for f in lot_flags:
        for fl in f.flags:
            flagged.setdefault((fl.lot, fl.unit), []).append(f"[{fl.kind}] {fl.reason}")
    in_lots = units["lot"].astype(str).isin(todo).to_numpy()
    keys = list(zip(units["lot"].astype(str), units["unit"].astype(str)))
    units["flagged"] = [
        bool(flagged.get(k)) if m else bool(v) if pd.notna(v) else False
        for k, m, v in zip(keys, in_lots, units.get("flagged", [False] * len(units)))
    ]
    units["flag_reason"] = [
        "; ".join(flagged.get(k, [])) if m else (v if isinstance(v, str) else "")
        for k, m, v in zip(keys, in_lots, units.get("flag_reason", [""] * len(units)))
    ]
    return units


def lots_to_reflag(
    known: dict[str, Any], files: dict[str, Any], touched: list[str]
) -> tuple[list[str], set[str]]:
    """(lots to re-flag, lots whose stored flags stand): a lot is re-flagged when the run
    touched it or its table files (``files``: lot -> file stats now) differ from those the
    flag state was kept with (``known``)."""
    dirty = sorted({lot for lot, f in files.items() if known.get(lot) != f} | set(map(str, touched)))
    return dirty, set(files) - set(dirty)


def has_small_lots(units: pd.DataFrame, config: OutlierConfig) -> bool:
    """Whether any lot of ``units`` (lot, unit rows) has fewer units than
    ``config.history_below``: such a lot is judged against the fleet history."""
    if not len(units):
        return False
    return bool((units.groupby("lot", observed=True)["unit"].nunique() < config.history_below).any())


def acquisition_seconds(units: pd.DataFrame) -> dict[tuple[str, str], float]:
    """(lot, unit) -> acquisition time of its current calibration (POSIX s): the units
    table's ``acquired_at`` (its sessions' last ``session_start``), else when it was
    calibrated (``calibrated_at``: units whose sessions carry no ``session_start``)."""
    if not len(units):
        return {}
    when = pd.Series(pd.NaT, index=units.index, dtype="datetime64[ns, UTC]")
    for col in ("calibrated_at", "acquired_at"):  # acquired_at wins where present
        if col in units:
            t = pd.to_datetime(units[col], utc=True, errors="coerce", format="ISO8601")
            when = t.where(t.notna(), when)
    secs = (when - pd.Timestamp(0, tz="UTC")).dt.total_seconds()
    return {
        (str(lot), str(u)): float(t) for lot, u, t in zip(units["lot"], units["unit"], secs) if pd.notna(t)
    }


def pooled_doc(pooled: dict[tuple[str, str], tuple[float, tuple[int, ...]]]) -> list:
    """The pooled scales as JSON values (floats round-trip exactly through JSON)."""
    return [[m, p, scale, list(sizes)] for (m, p), (scale, sizes) in sorted(pooled.items())]


def qa_status(lot_flags: LotFlags, unit: str, config: OutlierConfig, when: str) -> dict:
    """The QA block of a unit's calibration file: ``pass``, ``flagged`` (every reason) or
    ``limits`` (a limit failed: the failed limits, and every other reason too), and the lot
    context it was judged in."""
    mine = [f for f in lot_flags.flags if f.unit == unit]
    failed = [f"{f.reason}" for f in mine if f.kind == KIND_LIMIT]
    status = "limits" if failed else "flagged" if mine else "pass"
    return {
        "status": status,
        "reasons": [f"[{f.kind}] {f.reason}" for f in mine],
        "failed_limits": failed,
        "lot": lot_flags.lot,
        "lot_units": lot_flags.n_units,
        "reference": lot_flags.reference,
        "reference_detail": lot_flags.reference_detail,
        "z_threshold": lot_flags.z_threshold_used,
        "note": lot_flags.note,
        "config": {
            "z_threshold": config.z_threshold,
            "family_alpha": config.family_alpha,
            "spread_factor": config.spread_factor,
            "min_units": config.min_units,
            "scale_pool": config.scale_pool,
            "history_units": config.history_units,
            "history_below": config.history_below,
            "history_location": config.history_location,
            "limits": [f"{lim.model}.{lim.parameter}: {lim.written or ''}" for lim in config.limits],
        },
        "judged_at": when,
    }
