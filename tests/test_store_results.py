"""The results store: atomic tables, per-unit replacement, lock, calibration lookup."""

from __future__ import annotations

import threading
import time
from datetime import UTC, datetime
from pathlib import Path

import numpy as np
import pandas as pd
import pyarrow.parquet as pq
import pytest

from calib_core.calibration import Calibration
from flows.cli import main as cli_main
from schemas.calibration_file import load_calibration
from schemas.results_store import (
    CalibrationNotFound,
    ResultsStore,
    StoreLockedError,
    find_calibration,
    parse_when,
)


def temp_files(root: Path) -> list[Path]:
    return [p for p in root.rglob("*") if p.name.endswith(".tmp")]


def params(lot, unit, reps=(1, 2), value=1.0, run="r1"):
    return pd.DataFrame(
        [
            {
                "lot": lot,
                "unit": unit,
                "rep": r,
                "model": "gyro",
                "parameter": "k_g11",
                "value": value + r,
                "stderr": 1e-4,
                "unit_of_measure": "deg/s per deg/s",
                "code_version": "v",
                "run_id": run,
            }
            for r in reps
        ]
    )


def test_tables_round_trip_and_empty_tables_have_columns(tmp_path):
    st = ResultsStore(tmp_path)
    empty = st.read("sessions")
    assert len(empty) == 0 and list(empty.columns[:3]) == ["lot", "unit", "rep"]
    st.write("parameters", params("L1", "U1"))
    back = st.read("parameters")
    assert back["value"].tolist() == [2.0, 3.0]
    assert back["rep"].tolist() == [1, 2]
    assert temp_files(tmp_path) == []


def test_replace_units_touches_only_that_unit(tmp_path):
    st = ResultsStore(tmp_path)
    st.write("parameters", pd.concat([params("L1", "U1"), params("L1", "U2"), params("L2", "U3")]))
    before = st.read("parameters")
    st.replace_units("parameters", params("L1", "U2", reps=(1, 2, 3), value=10.0, run="r2"), {("L1", "U2")})
    after = st.read("parameters")
    others_before = before[before.unit != "U2"].reset_index(drop=True)
    others_after = after[after.unit != "U2"].reset_index(drop=True)
    pd.testing.assert_frame_equal(others_before, others_after)
    u2 = after[after.unit == "U2"]
    assert u2["value"].tolist() == [11.0, 12.0, 13.0] and set(u2.run_id) == {"r2"}


def test_failed_write_keeps_old_file_and_leaves_no_temp(tmp_path, monkeypatch):
    st = ResultsStore(tmp_path)
    st.write("parameters", params("L1", "U1"))
    lot_file = tmp_path / "tables" / "parameters" / "lot=L1.parquet"
    old = lot_file.read_bytes()

    def boom(*a, **k):
        raise OSError("disk full")

    monkeypatch.setattr(pq, "write_table", boom)
    with pytest.raises(OSError, match="disk full"):
        st.write("parameters", params("L1", "U1", value=5.0))
    assert lot_file.read_bytes() == old
    assert temp_files(tmp_path) == []
    assert st.read("parameters")["value"].tolist() == [2.0, 3.0]


def test_second_run_is_refused_with_the_holder_named(tmp_path):
    st = ResultsStore(tmp_path)
    with st.lock(owner="run-A"):
        with pytest.raises(StoreLockedError, match="run-A.*--wait"):
            with ResultsStore(tmp_path).lock(owner="run-B"):
                pass
    with st.lock(owner="run-C"):  # released: usable again
        pass


def test_waiting_run_gets_the_lock_when_released(tmp_path):
    st = ResultsStore(tmp_path)
    order = []
    st_lock = st.lock(owner="A")
    st_lock.__enter__()

    def second():
        with ResultsStore(tmp_path).lock(owner="B", wait=True, timeout=20, poll_s=0.05):
            order.append("B")

    t = threading.Thread(target=second)
    t.start()
    time.sleep(0.3)
    order.append("A-release")
    st_lock.__exit__(None, None, None)
    t.join(10)
    assert order == ["A-release", "B"]
    with pytest.raises(StoreLockedError):
        with st.lock(owner="C"):
            with ResultsStore(tmp_path).lock(owner="D", wait=True, timeout=0.2, poll_s=0.05):
                pass


def _cal(scale):
    return Calibration(K_g=np.eye(3) * scale, w0=np.zeros(3), K_a=np.eye(3), f0=np.zeros(3))


def test_calibrations_are_all_kept_and_found_by_date(tmp_path):
    st = ResultsStore(tmp_path)
    t1 = datetime(2026, 11, 1, 2, 0, tzinfo=UTC)
    t2 = datetime(2026, 11, 10, 2, 0, tzinfo=UTC)
    t3 = datetime(2026, 11, 20, 2, 0, tzinfo=UTC)
    p1 = st.save_calibration(_cal(1.0), "U1", {"provenance": {"run_id": "a"}}, t1)
    p2 = st.save_calibration(_cal(2.0), "U1", {"provenance": {"run_id": "b"}}, t2)
    p3 = st.save_calibration(_cal(3.0), "U1", {"provenance": {"run_id": "c"}}, t3)
    p3b = st.save_calibration(_cal(4.0), "U1", {}, t3)  # same instant: a new file, not overwritten
    assert p3b != p3 and load_calibration(p3).K_g[0, 0] == 3.0
    assert find_calibration(tmp_path, "U1", datetime(2026, 11, 15, tzinfo=UTC)) == p2
    assert find_calibration(tmp_path, "U1", t2) == p2  # at the instant itself
    assert find_calibration(tmp_path, "U1", datetime(2026, 11, 15, tzinfo=UTC), "after") == p3
    assert find_calibration(tmp_path, "U1", datetime(2026, 11, 9, tzinfo=UTC), "closest") == p2
    assert find_calibration(tmp_path, "U1", datetime(2026, 11, 2, tzinfo=UTC), "closest") == p1
    with pytest.raises(CalibrationNotFound, match="no calibration at or before"):
        find_calibration(tmp_path, "U1", datetime(2026, 10, 1, tzinfo=UTC))
    with pytest.raises(CalibrationNotFound, match="no calibration of unit 'U9'"):
        find_calibration(tmp_path, "U9")
    assert parse_when("2026-11-15") == datetime(2026, 11, 15, tzinfo=UTC)


def test_calibration_command(tmp_path, capsys):
    st = ResultsStore(tmp_path)
    t1 = datetime(2026, 11, 1, 2, 0, tzinfo=UTC)
    p1 = st.save_calibration(_cal(1.0), "U1", {}, t1)
    assert (
        cli_main(["calibration", "--results", str(tmp_path), "--unit", "U1", "--at", "2026-11-02T00:00:00Z"])
        == 0
    )
    assert capsys.readouterr().out.strip() == str(p1)
    assert cli_main(["calibration", "--results", str(tmp_path), "--unit", "U1", "--at", "2026-10-02"]) == 2
    assert "no calibration at or before" in capsys.readouterr().err
    assert cli_main(["calibration", "--results", str(tmp_path), "--unit", "U1", "--at", "yesterday"]) == 2
