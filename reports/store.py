"""Read access to the results store for the reports (never raw data).

Tables come through :class:`schemas.results_store.ResultsStore` (its column order and key
dtypes, either store format); a table that was never written is ``None`` so a report can say
so and still render. The store is partitioned by lot: a report of one lot or unit reads only
that lot's files (:meth:`StoreView.of`); only the fleet index reads whole tables.
"""

from __future__ import annotations

import json
from datetime import UTC, datetime
from functools import cached_property
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from schemas.results_store import ResultsStore

# Tables a report may use; missing ones are reported as missing, not an error.
REPORT_TABLES = (
    "sessions",
    "parameters",
    "summary",
    "units",
    "residuals",
    "compensation",
    "discovery",
    "navigation",
    "discovery_evidence",
)


def _keys_as_objects(df: pd.DataFrame) -> pd.DataFrame:
    """lot and unit as Python objects, None where missing. Through the distinct values (a
    lot's residual table has ~10^5 rows and 50 units): converting every row's string and
    then masking the missing ones cost ~0.15 s per lot."""
    for key in ("lot", "unit"):
        if key in df.columns:
            codes, uniques = pd.factorize(df[key], use_na_sentinel=True)
            lookup = np.empty(len(uniques) + 1, dtype=object)
            lookup[:-1] = np.asarray(uniques, dtype=object)
            lookup[-1] = None  # code -1: missing
            df[key] = pd.Series(lookup[codes], index=df.index, dtype=object)
    return df


class StoreView:
    """Cached, read-only view of one results root."""

    def __init__(self, results_root: str | Path) -> None:
        self.root = Path(results_root)
        self.store = ResultsStore(self.root)
        self._cache: dict[str, pd.DataFrame | None] = {}
        self._lot_cache: dict[tuple[str, str], pd.DataFrame | None] = {}

    @property
    def reports_dir(self) -> Path:
        return self.root / "reports"

    def table(self, name: str) -> pd.DataFrame | None:
        """The whole table (every lot); None when it was never written."""
        if name not in self._cache:
            df = self.store.read(name) if self.store.has_table(name) else None
            self._cache[name] = None if df is None else _keys_as_objects(df)
        return self._cache[name]

    def _lot_table(self, name: str, lot: str) -> pd.DataFrame | None:
        """One lot's rows of a table (only its file is read); None when the table does not
        exist."""
        if name in self._cache:  # the whole table is already in memory
            df = self._cache[name]
            return None if df is None else df[df["lot"] == lot]
        key = (name, lot)
        if key not in self._lot_cache:
            df = self.store.read(name, lots=[lot]) if self.store.has_table(name) else None
            self._lot_cache[key] = None if df is None else _keys_as_objects(df)
        return self._lot_cache[key]

    def of(self, name: str, lot: str | None = None, unit: str | None = None) -> pd.DataFrame | None:
        """Rows of a table for a lot and/or unit; None when the table does not exist."""
        if name == "navigation" and unit is not None and lot is not None and name not in self._cache:
            # raw-rate traces can be millions of rows: read only this unit's row groups
            return self._unit_rows(name, lot, unit)
        df = self.table(name) if lot is None else self._lot_table(name, lot)
        if df is None:
            return None
        m = pd.Series(True, index=df.index)
        if lot is not None and "lot" in df.columns:
            m &= df["lot"] == lot
        if unit is not None and "unit" in df.columns:
            m &= df["unit"] == unit
        return df[m]

    def _unit_rows(self, name: str, lot: str, unit: str) -> pd.DataFrame | None:
        if not self.store.has_table(name):
            return None
        legacy = self.store.legacy_path(name)
        path = legacy if legacy.exists() else self.store.partition_path(name, lot)
        if not path.exists():
            return _keys_as_objects(self.store.read(name, lots=[]))
        filters = [("unit", "==", unit), ("lot", "==", lot)]
        return pd.read_parquet(path, filters=filters)

    def forget_lot(self, lot: str) -> None:
        """Drop the cached rows of one lot (a pass over many lots keeps one lot in memory)."""
        for key in [k for k in self._lot_cache if k[1] == lot]:
            del self._lot_cache[key]

    def lots(self) -> list[str]:
        """Lots with rows in the units, sessions or summary table (from the lot files' names:
        no table is read)."""
        found: set[str] = set()
        for name in ("units", "sessions", "summary"):
            found |= set(self.store.table_lots(name))
        return sorted(found)

    def lot_of_unit(self, unit: str) -> str | None:
        for name in ("units", "summary", "sessions", "parameters"):
            df = self._cache.get(name)
            if df is None:
                if not self.store.has_table(name):
                    continue
                df = _keys_as_objects(self.store.read(name, columns=["lot", "unit"]))
            if len(df) and "unit" in df.columns:
                lots = df.loc[df["unit"] == unit, "lot"].dropna()
                if len(lots):
                    # a unit re-binned into another lot: the most recent rows win
                    return str(lots.iloc[-1])
        return None

    @cached_property
    def runs(self) -> list[dict[str, Any]]:
        """Run logs, oldest first, each with ``run_id`` and a parsed ``_time`` (or None)."""
        out = []
        for p in self.store.runs():
            try:
                doc = json.loads(p.read_text())
            except (OSError, ValueError):
                continue
            if not isinstance(doc, dict):
                continue
            doc.setdefault("run_id", p.stem)
            doc["_time"] = run_time(doc)
            out.append(doc)
        out.sort(key=lambda d: (d["_time"] is None, d["_time"] or datetime.min.replace(tzinfo=UTC)))
        return out

    def run(self, run_id: str | None) -> dict[str, Any] | None:
        for r in self.runs:
            if r.get("run_id") == run_id:
                return r
        return None

    def history(self, unit: str) -> list[dict[str, Any]]:
        """Every calibration file of a unit, oldest first: {time, path, doc}."""
        out = []
        for ts, path in self.store.calibration_files(unit):
            try:
                doc = json.loads(path.read_text())
            except (OSError, ValueError):
                continue
            out.append({"time": ts, "path": path, "doc": doc})
        return out

    def history_units(self) -> list[str]:
        d = self.root / "calibrations"
        return sorted(p.name for p in d.iterdir() if p.is_dir()) if d.is_dir() else []


def run_time(doc: dict[str, Any]) -> datetime | None:
    for key in ("finished_at", "ended_at", "end", "started_at", "start", "time"):
        v = doc.get(key)
        if v:
            try:
                t = datetime.fromisoformat(str(v).replace("Z", "+00:00"))
            except ValueError:
                continue
            return t if t.tzinfo else t.replace(tzinfo=UTC)
    return None


def provenance(doc: dict[str, Any]) -> dict[str, Any]:
    """Provenance of a calibration file wherever the writer put it."""
    out: dict[str, Any] = {}
    for key in ("metadata", "provenance"):
        v = doc.get(key)
        if isinstance(v, dict):
            out.update(v)
            if isinstance(v.get("provenance"), dict):
                out.update(v["provenance"])
    for key in ("run_id", "code_version", "lot", "unit"):
        if key in doc and key not in out:
            out[key] = doc[key]
    return out
