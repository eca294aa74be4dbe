"""Calibration history read from ``calibrations/<unit>/<timestamp>.json`` (every calibration
ever produced): the key parameters of each file as one row, for the unit report's history
and the fleet index's trends."""
from __future__ import annotations

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


def history_frame(view: StoreView, units: list[str] | None = None) -> pd.DataFrame:
    """One row per calibration file: unit, lot, time, run_id, code_version, file and the
    key elements (display units: f0 in mg)."""
    rows = []
    for unit in units if units is not None else view.history_units():
        lot_default = None
        for h in view.history(unit):
            doc = h["doc"]
            prov = provenance(doc)
            lot = prov.get("lot")
            if not lot:
                lot_default = lot_default or view.lot_of_unit(unit)
                lot = lot_default
            row = {"unit": unit, "lot": lot, "time": h["time"], "run_id": prov.get("run_id"),
                   "code_version": prov.get("code_version"), "file": h["path"].name}
            for _, name, key, i, j, scale, _ in KEY_ELEMENTS:
                row[name] = _element(doc, key, i, j) * scale
            rows.append(row)
    cols = ["unit", "lot", "time", "run_id", "code_version", "file"] + [e[1] for e in KEY_ELEMENTS]
    return pd.DataFrame(rows, columns=cols)
