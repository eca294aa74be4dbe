"""Calibration history read from ``calibrations/<unit>/<timestamp>.json`` (every calibration
ever produced): the key parameters of each file as one row, for the unit report's history
and the fleet index's trends."""
from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from reports.store import StoreView, provenance

# (group, element name, how to read it from the file, display scale, unit label)
KEY_ELEMENTS: list[tuple[str, str, str, int, int | None, float, str]] = (
    [("K_g", f"k_g{i + 1}{j + 1}", "K_g", i, j, 1.0, "") for i in range(3) for j in range(3)]
    + [("w0", f"w0_{a}", "w0", i, None, 1.0, "deg/s") for i, a in enumerate("xyz")]
    + [("K_a", f"k_a{i + 1}{j + 1}", "K_a", i, j, 1.0, "") for i in range(3) for j in range(3)]
    + [("f0", f"f0_{a}", "f0", i, None, 1e3, "mg") for i, a in enumerate("xyz")]
)
GROUP_TITLES = {"K_g": "Gyroscope K<sub>g</sub>", "w0": "Gyroscope bias ω<sub>0</sub> [deg/s]",
                "K_a": "Accelerometer K<sub>a</sub>", "f0": "Accelerometer bias f<sub>0</sub> [mg]"}


def _element(doc: dict[str, Any], key: str, i: int, j: int | None) -> float:
    try:
        v = doc[key][i] if j is None else doc[key][i][j]
        return float(v)
    except (KeyError, IndexError, TypeError, ValueError):
        return np.nan


# Parsed key elements of every calibration file, kept between processes: a file is never
# rewritten (ResultsStore.save_calibration makes a new one), so (name, size, mtime) says the
# entry is still that file's. Parsing ~200 files of ~30 kB costs ~0.2 s per fleet index.
HISTORY_CACHE_VERSION = 1


def history_cache_path(view: StoreView) -> Path:
    return view.root / "cache" / "report_history.json"


def _read_cache(view: StoreView) -> dict[str, Any]:
    try:
        doc = json.loads(history_cache_path(view).read_text())
    except (OSError, ValueError):
        return {}
    if not isinstance(doc, dict) or doc.get("version") != HISTORY_CACHE_VERSION \
            or not isinstance(doc.get("files"), dict):
        return {}
    return doc["files"]


def _write_cache(view: StoreView, files: dict[str, Any]) -> None:
    from reports.html import write_atomic
    try:  # a cache: a store we may not write to (or a full disk) only costs the parsing
        write_atomic(history_cache_path(view),
                     json.dumps({"version": HISTORY_CACHE_VERSION, "files": files}))
    except OSError:
        pass


def _parse_entry(path: Path, stat: os.stat_result) -> dict[str, Any] | None:
    """What history_frame needs of one calibration file; None when it cannot be read."""
    try:
        doc = json.loads(path.read_text())
    except (OSError, ValueError):
        return None
    prov = provenance(doc)
    return {"size": stat.st_size, "mtime_ns": stat.st_mtime_ns, "lot": prov.get("lot"),
            "run_id": prov.get("run_id"), "code_version": prov.get("code_version"),
            "values": [_element(doc, key, i, j) * scale for _, _, key, i, j, scale, _ in KEY_ELEMENTS]}


def history_frame(view: StoreView, units: list[str] | None = None) -> pd.DataFrame:
    """One row per calibration file: unit, lot, time, run_id, code_version, file and the
    key elements (display units: f0 in mg). The parsed elements of each file are cached in
    ``cache/report_history.json`` of the results root."""
    cache = _read_cache(view)
    seen: dict[str, Any] = {}
    parsed = False
    rows = []
    names = [e[1] for e in KEY_ELEMENTS]
    for unit in units if units is not None else view.history_units():
        lot_default = None
        for ts, path in view.store.calibration_files(unit):
            key = f"{unit}/{path.name}"
            try:
                st = path.stat()
            except OSError:
                continue
            entry = cache.get(key)
            if not (isinstance(entry, dict) and entry.get("size") == st.st_size
                    and entry.get("mtime_ns") == st.st_mtime_ns):
                entry = _parse_entry(path, st)
                if entry is None:
                    continue
                parsed = True
            seen[key] = entry
            lot = entry["lot"]
            if not lot:
                lot_default = lot_default or view.lot_of_unit(unit)
                lot = lot_default
            row = {"unit": unit, "lot": lot, "time": ts, "run_id": entry["run_id"],
                   "code_version": entry["code_version"], "file": path.name}
            row.update(zip(names, entry["values"]))
            rows.append(row)
    # a pass over every unit also forgets the files that are gone
    if parsed or (units is None and set(seen) != set(cache)):
        _write_cache(view, seen if units is None else {**cache, **seen})
    cols = ["unit", "lot", "time", "run_id", "code_version", "file"] + names
    return pd.DataFrame(rows, columns=cols)
