"""The results store partitioned by lot (format 2.0): one file per table and lot, reads of
some lots, writes that touch only their lots, and the transparent read and migration of a
format-1.0 store (one flat file per table at the root)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pandas as pd
import pyarrow as pa
import pyarrow.parquet as pq
import pytest

from schemas.results_store import (
    STORE_FORMAT_VERSION,
    TABLES,
    ResultsStore,
    StoreError,
    partition_file_name,
)
from schemas.store_frames import normalise

LOTS = ("L01", "L02", "L10")


def summary_rows(lot: str, units: list[str], seed: int, run: str = "r1") -> pd.DataFrame:
    rng = np.random.default_rng(seed)
    rows = []
    for u in units:
        for model, params in (("gyro", ("k_g11", "w0_x")), ("accel", ("k_a11", "f0_x"))):
            for p in params:
                rows.append(
                    {
                        "lot": lot,
                        "unit": u,
                        "model": model,
                        "parameter": p,
                        "mean": float(rng.normal()),
                        "std": float(rng.uniform()),
                        "min": -1.0,
                        "max": 1.0,
                        "n_reps": 5,
                        "unit_of_measure": "x",
                        "flagged": False,
                        "flag_reason": "",
                        "stale": False,
                        "stale_reason": "",
                        "run_id": run,
                    }
                )
    return pd.DataFrame(rows)


def residual_rows(lot: str, units: list[str], seed: int) -> pd.DataFrame:
    rng = np.random.default_rng(seed)
    n = 7
    return pd.DataFrame(
        {
            "lot": np.repeat([lot] * len(units), n * 2),
            "unit": np.repeat(units, n * 2),
            "rep": np.tile(np.repeat([1, 2], n), len(units)),
            "step": np.tile(np.arange(n), 2 * len(units)),
            "resid": rng.normal(size=2 * n * len(units)),
        }
    )


def fleet_tables() -> dict[str, pd.DataFrame]:
    """Summary and residual rows of 3 lots (given out of order, as a flow would)."""
    units = {lot: [f"U{i + 10 * k:04d}" for i in range(3)] for k, lot in enumerate(LOTS)}
    summ = pd.concat(
        [summary_rows(lot, units[lot], seed=k) for k, lot in enumerate(LOTS)][::-1], ignore_index=True
    )
    res = pd.concat(
        [residual_rows(lot, units[lot], seed=10 + k) for k, lot in enumerate(LOTS)][::-1], ignore_index=True
    )
    return {"summary": summ, "residuals": res}


def expected(df: pd.DataFrame, name: str) -> pd.DataFrame:
    """What format 1.0 gave back: the table normalised and sorted by its keys."""
    df = normalise(df.reset_index(drop=True), name)
    keys = [c for c in ("lot", "unit", "rep", "model", "parameter", "effect") if c in df]
    return df.sort_values(keys, kind="stable").reset_index(drop=True)


def file_state(path: Path) -> tuple[int, int]:
    st = path.stat()
    return st.st_ino, st.st_mtime_ns


def lot_files(store: ResultsStore, name: str) -> dict:
    return {lot: file_state(p) for lot, p in store.partitions(name).items()}


def test_one_file_per_lot_and_reads_give_the_sorted_table(tmp_path):
    st = ResultsStore(tmp_path)
    tabs = fleet_tables()
    for name, df in tabs.items():
        st.write(name, df)
        assert sorted(p.name for p in (tmp_path / "tables" / name).iterdir()) == [
            f"lot={lot}.parquet" for lot in LOTS
        ]
        back = st.read(name)
        pd.testing.assert_frame_equal(back, expected(df, name))
        one = st.read(name, lots=["L02"])
        pd.testing.assert_frame_equal(one, expected(df[df["lot"] == "L02"], name))
        two = st.read(name, lots={"L10", "L01"})
        pd.testing.assert_frame_equal(two, expected(df[df["lot"] != "L02"], name))
        assert len(st.read(name, lots=["nope"])) == 0
    assert st.table_lots("summary") == list(LOTS) and st.lots() == []
    cols = st.read("summary", lots=["L01"], columns=["unit", "mean", "score"])
    assert list(cols.columns) == ["unit", "mean", "score"] and cols["score"].isna().all()
    assert json.loads((tmp_path / "store.json").read_text())["format_version"] == "2.0"
    assert STORE_FORMAT_VERSION == "2.0" and st.format_version() == "2.0"


def test_replace_units_and_update_rows_rewrite_only_their_lot(tmp_path):
    st = ResultsStore(tmp_path)
    tabs = fleet_tables()
    for name, df in tabs.items():
        st.write(name, df)
    before = {n: lot_files(st, n) for n in tabs}
    full_before = st.read("residuals")
    new = residual_rows("L02", ["U0010"], seed=99)
    st.replace_units("residuals", new, {("L02", "U0010")})
    after = lot_files(st, "residuals")
    assert after["L01"] == before["residuals"]["L01"] and after["L10"] == before["residuals"]["L10"]
    assert after["L02"] != before["residuals"]["L02"]
    got = st.read("residuals")
    want = expected(pd.concat([full_before[full_before["unit"] != "U0010"], new]), "residuals")
    pd.testing.assert_frame_equal(got, want)
    st.update_rows("summary", {("L10", "U0020")}, stale=True, stale_reason="why")
    after = lot_files(st, "summary")
    assert after["L01"] == before["summary"]["L01"] and after["L02"] == before["summary"]["L02"]
    s = st.read("summary")
    hit = s["unit"] == "U0020"
    assert s.loc[hit, "stale"].all() and set(s.loc[hit, "stale_reason"]) == {"why"}
    assert not s.loc[~hit, "stale"].any()
    # a lot that loses its last rows loses its file; the table still exists, rows or not
    st.replace_units("residuals", None, {("L10", u) for u in ("U0020", "U0021", "U0022")})
    assert st.table_lots("residuals") == ["L01", "L02"]
    st.write("residuals", pd.DataFrame())
    assert st.partitions("residuals") == {} and st.has_table("residuals")
    assert len(st.read("residuals")) == 0 and not st.has_table("discovery")


def test_write_of_some_lots_refuses_rows_of_others_and_skips_unchanged(tmp_path):
    st = ResultsStore(tmp_path)
    df = fleet_tables()["summary"]
    st.write("summary", df)
    before = lot_files(st, "summary")
    with pytest.raises(ValueError, match="rows of lots"):
        st.write("summary", df, lots=["L01"])
    changed = st.read("summary")
    changed.loc[changed["lot"] == "L02", "score"] = 1.5
    written = st.write("summary", changed, skip_unchanged=True)
    assert written == ["L02"]
    after = lot_files(st, "summary")
    assert after["L01"] == before["L01"] and after["L10"] == before["L10"]
    assert (st.read("summary", lots=["L02"])["score"] == 1.5).all()
    # compared with the table as the caller read it (no second read of the files)
    before = lot_files(st, "summary")
    previous = st.read("summary")
    changed = previous.copy()
    changed.loc[changed["lot"] == "L10", "flagged"] = True
    assert st.write("summary", changed, skip_unchanged=True, previous=previous) == ["L10"]
    after = lot_files(st, "summary")
    assert after["L01"] == before["L01"] and after["L02"] == before["L02"]
    assert after["L10"] != before["L10"]
    got = st.read("summary")
    assert got.loc[got["lot"] == "L10", "flagged"].all() and not got.loc[got["lot"] != "L10", "flagged"].any()
    # the same strings built in memory (object dtype) as read back (string dtype): unchanged
    same = got.copy()
    same["flag_reason"] = [str(x) for x in got["flag_reason"]]
    same["flagged"] = [bool(x) for x in got["flagged"]]
    assert st.write("summary", same, skip_unchanged=True, previous=got) == []
    same.loc[0, "mean"] = same.loc[0, "mean"] + 1e-15  # any change of value is written
    assert st.write("summary", same, skip_unchanged=True, previous=got) == [same.loc[0, "lot"]]


def test_odd_lot_names_and_missing_lots_round_trip(tmp_path):
    st = ResultsStore(tmp_path)
    df = pd.concat([residual_rows("lot a/ü%", ["U1"], 1), residual_rows("L1", ["U2"], 2)], ignore_index=True)
    df.loc[df.index[-3:], "lot"] = None
    st.write("residuals", df)
    names = sorted(p.name for p in st.table_dir("residuals").iterdir())
    assert names == sorted([partition_file_name("lot a/ü%"), "lot=L1.parquet", "nolot.parquet"])
    assert "/" not in partition_file_name("lot a/ü%")[4:]
    pd.testing.assert_frame_equal(st.read("residuals"), expected(df, "residuals"))
    assert st.table_lots("residuals") == ["L1", "lot a/ü%"]
    assert len(st.read("residuals", lots=[None])) == 3


def write_flat_v1(root: Path, tables: dict[str, pd.DataFrame]) -> None:
    """A format-1.0 store as the old code wrote it: each table normalised, sorted, one file."""
    root.mkdir(parents=True, exist_ok=True)
    for name, df in tables.items():
        pq.write_table(
            pa.Table.from_pandas(expected(df, name), preserve_index=False),
            root / f"{name}.parquet",
            compression="zstd",
        )


def v1_tables() -> dict[str, pd.DataFrame]:
    tabs = fleet_tables()
    units = (
        tabs["summary"][["lot", "unit"]]
        .drop_duplicates()
        .assign(state="calibrated", reason="", n_sessions=5, flagged=False, flag_reason="")
    )
    sessions = (
        units[["lot", "unit"]]
        .merge(pd.DataFrame({"rep": [1, 2]}), how="cross")
        .assign(status="ok", fingerprint="f", run_id="r1")
    )
    return {**tabs, "units": units, "sessions": sessions}


def test_format_1_store_is_read_as_is_and_migrated_by_the_first_write(tmp_path):
    tabs = v1_tables()
    write_flat_v1(tmp_path, tabs)
    st = ResultsStore(tmp_path)
    assert st.format_version() == "1.0" and st.exists()
    for name, df in tabs.items():
        pd.testing.assert_frame_equal(st.read(name), expected(df, name))
        pd.testing.assert_frame_equal(st.read(name, lots=["L10"]), expected(df[df["lot"] == "L10"], name))
    assert st.table_lots("units") == list(LOTS) and st.lots() == list(LOTS)
    assert st.fingerprints()[("L02", "U0010", 2)] == "f"
    assert not st.tables_dir.exists()  # reading never writes
    # the first write migrates every table, then does its own change on the new layout
    new = residual_rows("L01", ["U0000"], seed=5)
    st.replace_units("residuals", new, {("L01", "U0000")})
    assert st.format_version() == "2.0"
    assert not any((tmp_path / f"{n}.parquet").exists() for n in TABLES)
    doc = json.loads((tmp_path / "store.json").read_text())
    assert doc["migrated_from"] == "1.0" and sorted(doc["migrated_tables"]) == sorted(tabs)
    for name, df in tabs.items():
        assert st.table_lots(name) == list(LOTS)
        if name == "residuals":
            df = pd.concat([df[df["unit"] != "U0000"], new])
        pd.testing.assert_frame_equal(st.read(name), expected(df, name))


def test_a_migration_that_died_half_way_is_redone_from_the_flat_file(tmp_path):
    tabs = v1_tables()
    write_flat_v1(tmp_path, tabs)
    st = ResultsStore(tmp_path)
    # a dead migration left lot files of the summary (one of a lot the flat file lacks)
    # next to the flat file, which is still the truth
    d = st.table_dir("summary")
    d.mkdir(parents=True)
    junk = summary_rows("L99", ["U9"], seed=1)
    pq.write_table(pa.Table.from_pandas(junk), d / "lot=L99.parquet")
    pq.write_table(pa.Table.from_pandas(summary_rows("L01", ["U9"], seed=1)), d / "lot=L01.parquet")
    pd.testing.assert_frame_equal(st.read("summary"), expected(tabs["summary"], "summary"))
    with st.lock(owner="migrating-run"):
        st.update_rows("units", {("L02", "U0011")}, reason="checked")
    assert not (tmp_path / "summary.parquet").exists()
    assert st.table_lots("summary") == list(LOTS)
    pd.testing.assert_frame_equal(st.read("summary"), expected(tabs["summary"], "summary"))
    units = st.read("units")
    assert units.loc[units["unit"] == "U0011", "reason"].tolist() == ["checked"]
    assert (units.loc[units["unit"] != "U0011", "reason"] == "").all()


def test_a_store_of_a_newer_format_is_refused_in_one_line_and_left_alone(tmp_path):
    st = ResultsStore(tmp_path)
    st.write("units", v1_tables()["units"])
    doc = json.loads((tmp_path / "store.json").read_text())
    (tmp_path / "store.json").write_text(json.dumps({**doc, "format_version": "3.0"}))
    before = {p: p.read_bytes() for p in tmp_path.rglob("*") if p.is_file()}
    fresh = ResultsStore(tmp_path)
    for act in (
        lambda: fresh.read("units"),
        lambda: fresh.update_rows("units", {("L01", "U0000")}, reason="x"),
        fresh.check,
    ):
        with pytest.raises(StoreError) as err:
            act()
        msg = str(err.value)
        assert "\n" not in msg and "format 3.0" in msg and "newer" in msg and str(tmp_path) in msg
    assert {p: p.read_bytes() for p in tmp_path.rglob("*") if p.is_file()} == before
    # an unknown older-looking version is refused as unknown, not migrated
    (tmp_path / "store.json").write_text(json.dumps({**doc, "format_version": "0.9"}))
    with pytest.raises(StoreError, match="unknown format '0.9'"):
        ResultsStore(tmp_path).read("units")


def test_stale_temp_files_in_table_directories_are_removed_by_the_lock_holder(tmp_path):
    st = ResultsStore(tmp_path)
    st.write("summary", fleet_tables()["summary"])
    stale = st.table_dir("summary") / ".lot=L01.parquet.ab12.tmp"
    stale.write_bytes(b"partial")
    with st.lock(owner="holder"):
        assert not stale.exists()
    assert st.table_lots("summary") == list(LOTS)
