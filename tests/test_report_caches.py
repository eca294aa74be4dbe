"""The fleet index's caches give what reading the store gives: the lots table's rows
(cache/fleet_index.json, valid while a lot's sessions and summary files are unchanged) and
the calibration files of each unit directory (cache/report_history.json "dirs")."""

from __future__ import annotations

import json
import os
import re
import time

import pandas as pd

from flows import runtime

runtime.ensure_environment()

from reports import history, index  # noqa: E402
from reports.store import StoreView  # noqa: E402
from tools.synthetic_store import build_synthetic_store  # noqa: E402


def _rows_from_tables(view: StoreView) -> dict[str, dict]:
    """The lots table's rows from the whole tables, as the index computed them before."""
    sessions, summary = view.table("sessions"), view.table("summary")
    return {
        lot: index._lot_row(sessions[sessions["lot"] == lot], summary[summary["lot"] == lot])
        for lot in view.lots()
    }


def _text(root) -> str:
    text = index.render_fleet_index(root, StoreView(root))
    return re.sub(r"generated \d{4}-\d{2}-\d{2} \d{2}:\d{2} UTC", "generated T", text)


def test_lot_rows_cache_follows_the_lot_files(tmp_path):
    truth = build_synthetic_store(
        tmp_path / "s", n_units=8, n_outliers=1, n_failed=1, seed=3, nav_samples=100
    )
    view = StoreView(truth.root)
    cache = index.fleet_index_cache_path(view)
    assert not cache.exists()
    cold = _text(truth.root)
    assert cache.exists()
    want = _rows_from_tables(StoreView(truth.root))
    assert index.lot_rows(StoreView(truth.root), list(want)) == want
    assert _text(truth.root) == cold  # from the cache
    # the lot's summary rewritten with one more flagged unit: its row is computed again
    store = view.store
    summary = store.read("summary")
    unflagged = sorted(set(summary["unit"]) - set(summary.loc[summary["flagged"].astype(bool), "unit"]))
    summary.loc[summary["unit"] == unflagged[0], "flagged"] = True
    store.write("summary", summary)
    rows = index.lot_rows(StoreView(truth.root), [truth.lot])
    assert unflagged[0] in rows[truth.lot]["flagged"]
    assert rows == _rows_from_tables(StoreView(truth.root))
    # a broken cache is rebuilt
    cache.write_text("{not json")
    assert index.lot_rows(StoreView(truth.root), [truth.lot]) == rows
    assert json.loads(cache.read_text())["lots"][truth.lot]["row"] == rows[truth.lot]


def test_lot_rows_of_a_format_1_store(tmp_path):
    """A format-1.0 store (flat table files) is read whole, as before, without cache."""
    truth = build_synthetic_store(
        tmp_path / "s", n_units=6, n_outliers=1, n_failed=0, seed=4, nav_samples=100
    )
    view = StoreView(truth.root)
    want = _rows_from_tables(view)
    for name in ("sessions", "summary"):
        df = view.store.read(name)
        for p in view.store.partitions(name).values():
            p.unlink()
        view.store.table_dir(name).rmdir()
        df.to_parquet(view.store.legacy_path(name))
    legacy = StoreView(truth.root)
    assert legacy.store.partition_stats("summary") is None
    assert index.lot_rows(legacy, legacy.lots()) == want
    assert not index.fleet_index_cache_path(legacy).exists()


def test_history_directory_cache(tmp_path):
    truth = build_synthetic_store(
        tmp_path / "s", n_units=4, n_outliers=0, n_failed=0, seed=5, nav_samples=100
    )
    view = StoreView(truth.root)
    units = view.history_units()
    # directories settle (their mtime a few seconds old) before they are cached
    old = time.time() - 60
    for u in units:
        os.utime(view.store.calibrations_dir / u, (old, old))
    cold = history.history_frame(view)
    doc = json.loads(history.history_cache_path(view).read_text())
    assert sorted(doc["dirs"]) == units
    warm = history.history_frame(StoreView(truth.root))
    pd.testing.assert_frame_equal(cold, warm)
    # a new calibration file changes its directory's mtime: it is listed again
    u0 = units[0]
    first = view.store.calibration_files(u0)[0][1]
    new = first.with_name("20300101T000000.000000Z.json")
    new.write_text(first.read_text())
    again = history.history_frame(StoreView(truth.root))
    assert list(again.loc[again["unit"] == u0, "file"])[-1] == new.name
    assert len(again) == len(cold) + 1
    # a file edited in place (directory unchanged) is still parsed again
    os.utime(view.store.calibrations_dir / u0, (old, old))
    history.history_frame(StoreView(truth.root))  # caches the directory with the new file
    d = json.loads(new.read_text())
    d["K_g"][0][0] = 1.25
    new.write_text(json.dumps(d))
    os.utime(view.store.calibrations_dir / u0, (old, old))
    edited = history.history_frame(StoreView(truth.root))
    assert edited.loc[edited["file"] == new.name, "k_g11"].item() == 1.25
    # a cache written by older code (no "dirs") is read as before
    doc = json.loads(history.history_cache_path(view).read_text())
    history.history_cache_path(view).write_text(
        json.dumps({"version": doc["version"], "files": doc["files"]})
    )
    pd.testing.assert_frame_equal(history.history_frame(StoreView(truth.root)), edited)
