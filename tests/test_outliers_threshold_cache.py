"""The simulated outlier thresholds live in a ThresholdTable the caller owns for one run (the
flows keep its document in the results store between runs); a stale or foreign document is
not trusted, and calib_core keeps nothing between calls."""

from __future__ import annotations

import json

import pandas as pd

from calib_core import outliers as o
from schemas.results_store import ResultsStore


def test_a_taken_threshold_is_used_instead_of_simulating():
    table = o.ThresholdTable()
    q = table.robust_z((7, 9), 24, 3.5, 0.01)  # simulated here
    doc = table.document()
    assert [e["group_sizes"] for e in doc["thresholds"]] == [[7, 9]]
    json.dumps(doc)  # JSON-ready
    # a planted value proves that the taken one is returned (no simulation)
    doc["thresholds"][0]["q"] = 9.25
    planted = o.ThresholdTable(doc)
    assert len(planted) == 1
    assert planted.robust_z((9, 7), 24, 3.5, 0.01) == 9.25  # order of lots irrelevant
    # the kept value of a real run equals the simulation, and a fresh simulation gives it again
    doc["thresholds"][0]["q"] = q
    assert o.ThresholdTable(doc).robust_z((7, 9), 24, 3.5, 0.01) == q
    assert o.robust_z_threshold((7, 9), 24, 3.5, 0.01) == q


def test_another_simulation_version_or_bad_entries_are_ignored():
    good = {"group_sizes": [5], "n_parameters": 3, "z_threshold": 3.5, "family_alpha": 0.01, "q": 99.0}
    table = o.ThresholdTable()
    assert table.take({"version": o.THRESHOLD_SIMULATION_VERSION + 1, "thresholds": [good]}) == 0
    assert table.take(None) == 0
    bad = [{"group_sizes": "x"}, {**good, "q": float("nan")}, {**good, "q": "abc"}]
    assert table.take({"version": o.THRESHOLD_SIMULATION_VERSION, "thresholds": bad}) == 0
    assert len(table) == 0
    assert table.robust_z(5, 3, 3.5, 0.01) != 99.0


def _summary(lots: dict[str, int]) -> pd.DataFrame:
    rows = []
    for lot, n in lots.items():
        for u in range(n):
            rows.append(
                dict(
                    lot=lot,
                    unit=f"U{u:02d}",
                    model="gyro",
                    parameter="w0_x",
                    mean=0.01 * u,
                    std=0.1,
                    n_reps=5,
                )
            )
    return pd.DataFrame(rows)


def test_flag_lots_fills_the_table_it_is_given_and_nothing_else():
    summary = _summary({"A": 7, "B": 9})
    table = o.ThresholdTable()
    first = o.flag_lots(summary, thresholds=table)
    assert [e["group_sizes"] for e in table.document()["thresholds"]] == [[7, 9]]
    # a second run handed the first run's document simulates nothing new and flags the same
    again = o.ThresholdTable(table.document())
    second = o.flag_lots(summary, thresholds=again)
    assert again.document() == table.document()
    assert [f.z_threshold_used for f in first] == [f.z_threshold_used for f in second]
    # without a table, every call starts afresh: no state is left in the module
    assert not [name for name, v in vars(o).items() if isinstance(v, dict) and name.isupper()]


def test_the_store_keeps_the_document_and_survives_a_corrupt_one(tmp_path):
    store = ResultsStore(tmp_path)
    assert store.read_outlier_thresholds() is None
    doc = {"version": 1, "thresholds": []}
    store.write_outlier_thresholds(doc)
    assert store.read_outlier_thresholds() == doc
    store.outlier_thresholds_path.write_text("{not json")
    assert store.read_outlier_thresholds() is None
