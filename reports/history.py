"""Calibration history read from ``calibrations/<unit>/<timestamp>.json`` (every calibration
ever produced): the key parameters of each file as one row, for the unit report's history
and the fleet index's trends."""

from __future__ import annotations

import json
import os
import time
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from reports.store import StoreView, provenance
from schemas.display import value_unit
from schemas.results_store import TIMESTAMP_FORMAT

_F0 = value_unit("g")  # accelerometer biases, stored in g, shown in mg (schemas.display)
# (group, element name, how to read it from the file, display scale, unit label)
KEY_ELEMENTS: list[tuple[str, str, str, int, int | None, float, str]] = (
    [("K_g", f"k_g{i + 1}{j + 1}", "K_g", i, j, 1.0, "") for i in range(3) for j in range(3)]
    + [("w0", f"w0_{a}", "w0", i, None, 1.0, "deg/s") for i, a in enumerate("xyz")]
    + [("K_a", f"k_a{i + 1}{j + 1}", "K_a", i, j, 1.0, "") for i in range(3) for j in range(3)]
    + [("f0", f"f0_{a}", "f0", i, None, _F0.factor, _F0.label) for i, a in enumerate("xyz")]
)
GROUP_TITLES = {
    "K_g": "Gyroscope K<sub>g</sub>",
    "w0": "Gyroscope bias ω<sub>0</sub> [deg/s]",
    "K_a": "Accelerometer K<sub>a</sub>",
    "f0": "Accelerometer bias f<sub>0</sub> [mg]",
}


def _element(doc: dict[str, Any], key: str, i: int, j: int | None) -> float:
    try:
        v = doc[key][i] if j is None else doc[key][i][j]
        return float(v)
    except (KeyError, IndexError, TypeError, ValueError):
        return np.nan


# Parsed key elements of every calibration file, kept between processes: a file is never
# rewritten (ResultsStore.save_calibration makes a new one), so (name, size, mtime) says the
# entry is still that file's. Parsing ~200 files of ~30 kB costs ~0.2 s per fleet index.
# Besides, each unit's directory: its (mtime, inode) and the calibration files it held. A
# directory whose mtime is unchanged has had no file added, removed or renamed in it, so its
# files are the cached ones and it need not be listed (globbing 1,000 units' directories cost
# ~0.1 s per fleet index; each file's size and mtime are still checked). Older code reads the
# same document and ignores "dirs".
HISTORY_CACHE_VERSION = 2  # 2: entries hold the acquisition time and the QA status
DIR_SETTLED_NS = 2_000_000_000


def history_cache_path(view: StoreView) -> Path:
    return view.root / "cache" / "report_history.json"


def _read_cache(view: StoreView) -> tuple[dict[str, Any], dict[str, Any]]:
    """(file entries, directory entries) of the cache; empty when missing or foreign."""
    try:
        doc = json.loads(history_cache_path(view).read_text())
    except (OSError, ValueError):
        return {}, {}
    if (
        not isinstance(doc, dict)
        or doc.get("version") != HISTORY_CACHE_VERSION
        or not isinstance(doc.get("files"), dict)
    ):
        return {}, {}
    dirs = doc.get("dirs")
    return doc["files"], dirs if isinstance(dirs, dict) else {}


def _write_cache(view: StoreView, files: dict[str, Any], dirs: dict[str, Any]) -> None:
    from reports.html import write_atomic

    try:  # a cache: a store we may not write to (or a full disk) only costs the parsing
        write_atomic(
            history_cache_path(view),
            json.dumps({"version": HISTORY_CACHE_VERSION, "files": files, "dirs": dirs}),
        )
    except OSError:
        pass


def _parse_entry(path: Path, stat: os.stat_result) -> dict[str, Any] | None:
    """What history_frame needs of one calibration file; None when it cannot be read."""
    try:
        doc = json.loads(path.read_text())
    except (OSError, ValueError):
        return None
    prov = provenance(doc)
    qa = doc.get("qa") if isinstance(doc.get("qa"), dict) else {}
    return {
        "size": stat.st_size,
        "mtime_ns": stat.st_mtime_ns,
        "lot": prov.get("lot"),
        "run_id": prov.get("run_id"),
        "code_version": prov.get("code_version"),
        "acquired_at": prov.get("acquired_at") if isinstance(prov.get("acquired_at"), str) else None,
        "qa_status": qa.get("status"),
        "values": [_element(doc, key, i, j) * scale for _, _, key, i, j, scale, _ in KEY_ELEMENTS],
    }


def _unit_entries(
    view: StoreView, unit: str, cache: dict[str, Any], dirs: dict[str, Any]
) -> tuple[list[tuple[Any, Path, dict[str, Any]]], Any, bool]:
    """(time, path, entry) of each readable calibration file of ``unit``, oldest first; the
    unit directory's cache entry (None: not cacheable); whether a file was parsed."""
    d = view.store.calibrations_dir / unit
    try:
        st = d.stat()
        dir_key = [st.st_mtime_ns, st.st_ino]
    except OSError:
        dir_key = None
    known = dirs.get(unit)
    if (
        dir_key is not None
        and isinstance(known, dict)
        and known.get("stat") == dir_key
        and isinstance(known.get("files"), list)
    ):
        # no file added, removed or renamed since: the cached names, oldest first
        files = [
            (datetime.strptime(name[: -len(".json")], TIMESTAMP_FORMAT).replace(tzinfo=UTC), d / name)
            for name in known["files"]
        ]
    else:
        files = view.store.calibration_files(unit)
    out, parsed = [], False
    for ts, path in files:
        key = f"{unit}/{path.name}"
        try:
            fst = path.stat()
        except OSError:  # removed meanwhile: the directory is listed again next time
            continue
        entry = cache.get(key)
        if not (
            isinstance(entry, dict)
            and entry.get("size") == fst.st_size
            and entry.get("mtime_ns") == fst.st_mtime_ns
        ):
            entry = _parse_entry(path, fst)
            if entry is None:
                continue
            parsed = True
        out.append((ts, path, entry))
    # a directory is cached with its readable files only when all were (an unreadable file
    # is tried again next time, as before), and only once its mtime is a few seconds old: a
    # file added within the same timestamp tick as the listing would not change the mtime
    cacheable = (
        dir_key is not None and len(out) == len(files) and dir_key[0] < time.time_ns() - DIR_SETTLED_NS
    )
    return out, ({"stat": dir_key, "files": [p.name for _, p, _ in out]} if cacheable else None), parsed


def _when(text: Any) -> datetime | None:
    if not isinstance(text, str) or not text:
        return None
    try:
        from schemas.results_store import parse_when

        return parse_when(text)
    except ValueError:
        return None


def history_frame(view: StoreView, units: list[str] | None = None) -> pd.DataFrame:
    """One row per calibration file: unit, lot, time (when the unit was measured: the
    sessions' last ``session_start``, else when the file was produced; ``time_source`` says
    which), produced, qa_status, run_id, code_version, file and the key elements (display
    units: f0 in mg). The parsed elements of each file, and the files
    of each unit directory, are cached in ``cache/report_history.json`` of the results root."""
    cache, dirs = _read_cache(view)
    seen: dict[str, Any] = {}
    seen_dirs: dict[str, Any] = {}
    parsed = False
    rows = []
    names = [e[1] for e in KEY_ELEMENTS]
    for unit in units if units is not None else view.history_units():
        lot_default = None
        entries, dir_entry, unit_parsed = _unit_entries(view, unit, cache, dirs)
        parsed |= unit_parsed
        if dir_entry is not None:
            seen_dirs[unit] = dir_entry
        for ts, path, entry in entries:
            seen[f"{unit}/{path.name}"] = entry
            lot = entry["lot"]
            if not lot:
                lot_default = lot_default or view.lot_of_unit(unit)
                lot = lot_default
            acquired = _when(entry.get("acquired_at"))
            row = {
                "unit": unit,
                "lot": lot,
                "time": acquired or ts,
                "produced": ts,
                "time_source": "session_start" if acquired else "processing time",
                "qa_status": entry.get("qa_status"),
                "run_id": entry["run_id"],
                "code_version": entry["code_version"],
                "file": path.name,
            }
            row.update(zip(names, entry["values"]))
            rows.append(row)
    # a pass over every unit also forgets the files and directories that are gone
    if units is None:
        changed = set(seen) != set(cache) or seen_dirs != dirs
        files, dirs_out = seen, seen_dirs
    else:
        changed = any(dirs.get(u) != e for u, e in seen_dirs.items())
        files, dirs_out = {**cache, **seen}, {**dirs, **seen_dirs}
    if parsed or changed:
        _write_cache(view, files, dirs_out)
    cols = [
        "unit",
        "lot",
        "time",
        "produced",
        "time_source",
        "qa_status",
        "run_id",
        "code_version",
        "file",
    ] + names
    return pd.DataFrame(rows, columns=cols)
