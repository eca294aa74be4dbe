"""The simulated outlier thresholds survive the process (calib_core.outliers known/remember,
kept by the flows in the results store), and a stale or foreign cache is not trusted."""

from __future__ import annotations

import json

from calib_core import outliers as o
from schemas.results_store import ResultsStore


def _fresh(monkeypatch):
    monkeypatch.setattr(o, "_KNOWN_THRESHOLDS", {})
    o.robust_z_threshold.cache_clear()


def test_a_remembered_threshold_is_used_instead_of_simulating(monkeypatch):
    _fresh(monkeypatch)
    q = o.robust_z_threshold((7, 9), 24, 3.5, 0.01)  # simulated here
    doc = o.known_thresholds()
    assert [e["group_sizes"] for e in doc["thresholds"]] == [[7, 9]]
    json.dumps(doc)  # JSON-ready
    _fresh(monkeypatch)
    # a planted value proves that the remembered one is returned (no simulation)
    doc["thresholds"][0]["q"] = 9.25
    assert o.remember_thresholds(doc) == 1
    assert o.robust_z_threshold((9, 7), 24, 3.5, 0.01) == 9.25  # order of lots irrelevant
    # the remembered value of a real run equals the simulation
    _fresh(monkeypatch)
    doc["thresholds"][0]["q"] = q
    o.remember_thresholds(doc)
    assert o.robust_z_threshold((7, 9), 24, 3.5, 0.01) == q


def test_another_simulation_version_or_bad_entries_are_ignored(monkeypatch):
    _fresh(monkeypatch)
    good = {"group_sizes": [5], "n_parameters": 3, "z_threshold": 3.5, "family_alpha": 0.01, "q": 99.0}
    assert o.remember_thresholds({"version": o.THRESHOLD_SIMULATION_VERSION + 1, "thresholds": [good]}) == 0
    assert o.remember_thresholds(None) == 0
    bad = [{"group_sizes": "x"}, {**good, "q": float("nan")}, {**good, "q": "abc"}]
    assert o.remember_thresholds({"version": o.THRESHOLD_SIMULATION_VERSION, "thresholds": bad}) == 0
    assert o.robust_z_threshold(5, 3, 3.5, 0.01) != 99.0


def test_the_store_keeps_the_document_and_survives_a_corrupt_one(tmp_path):
    store = ResultsStore(tmp_path)
    assert store.read_outlier_thresholds() is None
    doc = {"version": 1, "thresholds": []}
    store.write_outlier_thresholds(doc)
    assert store.read_outlier_thresholds() == doc
    store.outlier_thresholds_path.write_text("{not json")
    assert store.read_outlier_thresholds() is None
