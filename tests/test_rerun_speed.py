"""The rerun's speed-ups keep its outputs: the reflag's changed-lot test agrees with the
store's own skip-unchanged comparison, reports written through one shared store view equal
reports written one by one, and the import thread reports what it did."""

from __future__ import annotations

import re

import numpy as np
import pandas as pd
import pytest

from flows import runtime

runtime.ensure_environment()

from calib_core.flag_decisions import lots_with_new_flags  # noqa: E402
from flows import nightly  # noqa: E402
from reports.index import write_fleet_index  # noqa: E402
from reports.lot import write_lot_report  # noqa: E402
from reports.unit import write_unit_report  # noqa: E402
from schemas.results_store import ResultsStore  # noqa: E402
from tools.synthetic_store import build_synthetic_store  # noqa: E402


def _summary(rng: np.random.Generator, lots: list[str], units_per_lot: int = 6) -> pd.DataFrame:
    rows = []
    for lot in lots:
        for u in range(units_per_lot):
            for p in ("k_g11", "w0_x", "k_a11"):
                rows.append(
                    {
                        "lot": lot,
                        "unit": f"{lot}-U{u}",
                        "model": "gyro",
                        "parameter": p,
                        "mean": rng.normal(),
                        "std": abs(rng.normal()),
                        "min": -1.0,
                        "max": 1.0,
                        "n_reps": 5,
                        "unit_of_measure": "",
                        "flagged": False,
                        "flag_reason": "",
                        "score": rng.normal(),
                        "lot_median": rng.normal(),
                        "stale": False,
                        "stale_reason": "",
                        "run_id": "r1",
                    }
                )
    return pd.DataFrame(rows)


def test_changed_lots_are_the_lots_the_store_would_rewrite(tmp_path):
    rng = np.random.default_rng(3)
    lots = ["A", "B", "C", "D", "E", "F"]
    store = ResultsStore(tmp_path)
    store.write("summary", _summary(rng, lots))
    before = store.read("summary")
    # the stored frame has NaN scores in lot F: NaN must equal NaN
    before.loc[before["lot"] == "F", "score"] = np.nan
    store.write("summary", before)
    before = store.read("summary")
    after = before.copy()
    a = (after["lot"] == "A").to_numpy()
    after.loc[np.flatnonzero(a)[0], "score"] += 1e-12  # a score moved by rounding: changed
    b = np.flatnonzero((after["lot"] == "B").to_numpy())[1]
    after.loc[b, "flagged"] = True  # a new flag
    after.loc[b, "flag_reason"] = "[robust_z] far out"
    d = np.flatnonzero((after["lot"] == "D").to_numpy())[2]
    after.loc[d, "lot_median"] = np.nan  # a value became missing
    # C, E, F: the same values (F's NaN scores stay NaN)
    expected = ["A", "B", "D"]
    assert lots_with_new_flags(before, after) == expected
    # the store's own decision (skip_unchanged against the frame read) agrees
    assert sorted(store.write("summary", after, skip_unchanged=True, previous=before)) == expected


def test_changed_lots_missing_flag_column_means_every_lot():
    before = _summary(np.random.default_rng(4), ["A", "B"]).drop(columns=["score"])
    after = before.assign(score=0.0)
    assert lots_with_new_flags(before, after) == ["A", "B"]


def _normalised(text: str) -> str:
    # the generation time is the only thing that differs between two writes of a report
    return re.sub(r"generated \d{4}-\d{2}-\d{2} \d{2}:\d{2} UTC", "generated T", text)


def test_reports_through_one_view_equal_reports_written_one_by_one(tmp_path):
    truth = build_synthetic_store(
        tmp_path / "a", n_units=8, n_outliers=1, n_failed=1, seed=5, nav_samples=500
    )
    unit = truth.units[0]
    separate = [
        write_unit_report(truth.root, unit).read_text(),
        write_lot_report(truth.root, truth.lot).read_text(),
        write_fleet_index(truth.root).read_text(),
    ]
    written, problems = nightly.write_reports(truth.root, [truth.lot], units=(unit,))
    assert problems == []
    assert [p.rsplit("/", 1)[-1] for p in written] == [f"{unit}.html", f"{truth.lot}.html", "index.html"]
    shared = [open(p).read() for p in written]
    assert [_normalised(t) for t in shared] == [_normalised(t) for t in separate]


def test_preload_imports_in_a_thread_and_reports_failures():
    pre = nightly._Preload(("json", "no_such_module_mimucal"))
    info = pre.wait()
    assert info["modules"] == 2
    assert info["waited_in_flow_s"] >= 0.0 and info["import_wall_s"] >= 0.0
    assert len(info["failed"]) == 1 and info["failed"][0].startswith("no_such_module_mimucal")


@pytest.mark.parametrize("name", nightly.FLOW_PRELOAD)
def test_preloaded_modules_exist(name):
    import importlib

    importlib.import_module(name)


def test_history_cache_gives_the_rows_of_the_files(tmp_path):
    from reports import history
    from reports.store import StoreView

    truth = build_synthetic_store(
        tmp_path / "s", n_units=5, n_outliers=0, n_failed=0, seed=9, nav_samples=100
    )
    view = StoreView(truth.root)
    path = history.history_cache_path(view)
    assert not path.exists()
    cold = history.history_frame(view)
    assert path.exists() and len(cold) > 0
    # the rows straight from the files (independent of the cache): one per file
    files = [(u, p) for u in view.history_units() for _, p in view.store.calibration_files(u)]
    assert sorted(zip(cold["unit"], cold["file"])) == sorted((u, p.name) for u, p in files)
    u0, p0 = files[0]
    doc = __import__("json").loads(p0.read_text())
    row = cold[(cold["unit"] == u0) & (cold["file"] == p0.name)].iloc[0]
    assert row["k_g11"] == doc["K_g"][0][0] and row["f0_z"] == doc["f0"][2] * 1e3
    warm = history.history_frame(StoreView(truth.root))
    pd.testing.assert_frame_equal(cold, warm)
    # a stale entry (the file changed) is parsed again, a broken cache is ignored
    p0.write_text(p0.read_text().replace(repr(doc["K_g"][0][0]), "1.5", 1))
    again = history.history_frame(StoreView(truth.root))
    assert again.loc[(again["unit"] == u0) & (again["file"] == p0.name), "k_g11"].iloc[0] == 1.5
    path.write_text("{not json")
    pd.testing.assert_frame_equal(history.history_frame(StoreView(truth.root)), again)
    # one unit's pass keeps the other units' entries
    history.history_frame(StoreView(truth.root), [u0])
    cached = __import__("json").loads(path.read_text())["files"]
    assert len(cached) == len(files)
