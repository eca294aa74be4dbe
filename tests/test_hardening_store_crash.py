"""Issue 8 item 3, deterministically: the run dies between two writes of the results store.

Every store file is replaced atomically, so a crash leaves the store exactly as it was after
the last completed write. Here the nightly run (in process) is stopped right after its k-th
table write, for every k, then rerun; the rerun must give the same results as an
uninterrupted run (compared as in test_hardening_crash.py, which does the same with SIGKILL
on real processes at points it cannot choose this precisely).

Also: temp files left by a writer killed mid-write are removed by the next run that holds
the lock, and never by a run that does not."""

from __future__ import annotations

import json
from pathlib import Path

import pandas as pd
import pytest

from flows import runtime

runtime.ensure_environment()

from flows.fleet_sim import simulate_fleet  # noqa: E402
from flows.nightly import nightly_fleet_calibration  # noqa: E402
from schemas.results_store import TABLES, ResultsStore, StoreLockedError  # noqa: E402

VOLATILE_COLUMNS = ("run_id", "calibrated_at", "updated_at", "calibration_file", "code_version")


class SimulatedCrash(Exception):
    """Stands for the process dying: nothing after it is written."""


def comparable(results: Path) -> tuple[dict, dict]:
    store = ResultsStore(results)
    tables = {
        n: store.read(n).drop(columns=[c for c in VOLATILE_COLUMNS if c in store.read(n).columns])
        for n in TABLES
    }
    cals = {}
    for r in store.read("units").itertuples():
        doc = json.loads((results / r.calibration_file).read_text())
        for k in ("run_id", "calibrated_at", "code_version"):
            doc["provenance"].pop(k)
        (doc.get("qa") or {}).pop("judged_at", None)  # when the lot was re-flagged
        cals[str(r.unit)] = doc
    return tables, cals


@pytest.fixture(scope="module")
def fleet(tmp_path_factory):
    base = tmp_path_factory.mktemp("storecrash")
    data = base / "data"
    simulate_fleet(data, lots=1, units=4, reps=2, seed=5, sample_rate_hz=10.0, bad_sessions=1)
    clean = base / "clean"
    nightly_fleet_calibration(data, clean, run_discovery=False, progress=False)
    return base, data, comparable(clean)


@pytest.mark.slow
@pytest.mark.parametrize("crash_after", [1, 3, 6])
def test_crash_after_any_table_write_then_rerun_gives_the_clean_results(fleet, crash_after, monkeypatch):
    base, data, (clean_tables, clean_cals) = fleet
    results = base / f"crash-{crash_after}"
    original = ResultsStore.write
    calls = []

    def dying_write(self, name, df, *args, **kwargs):
        original(self, name, df, *args, **kwargs)
        calls.append(name)
        if len(calls) == crash_after:
            raise SimulatedCrash(f"died after writing table {name}")

    monkeypatch.setattr(ResultsStore, "write", dying_write)
    with pytest.raises(Exception) as info:
        nightly_fleet_calibration(data, results, run_discovery=False, progress=False)
    assert "died after writing" in str(info.value)
    monkeypatch.setattr(ResultsStore, "write", original)
    log = nightly_fleet_calibration(data, results, run_discovery=False, progress=False)
    tables, cals = comparable(results)
    for name in TABLES:
        pd.testing.assert_frame_equal(tables[name], clean_tables[name], obj=f"{name}.parquet")
    assert cals == clean_cals
    # before sessions.parquet (the fingerprints) the units are redone; after it they are done
    assert log["units_calibrated"] == (0 if "sessions" in calls else 4), calls
    # the crashed run's log has no end; the rerun says it recovered it, and marks it
    store = ResultsStore(results)
    crashed = [p.stem for p in store.runs() if p.stem != log["run_id"]]
    assert len(crashed) == 1 and log["recovering_runs"] == crashed
    doc = store.read_run(crashed[0])
    assert "end" not in doc and doc["interrupted"] and doc["recovered_by"] == log["run_id"]
    # a third run has nothing to recover and nothing to do
    again = nightly_fleet_calibration(data, results, run_discovery=False, progress=False)
    assert "recovering_runs" not in again and again["units_calibrated"] == 0


def test_stale_temp_files_are_removed_by_the_next_lock_holder(tmp_path):
    store = ResultsStore(tmp_path)
    (tmp_path / "calibrations" / "U1").mkdir(parents=True)
    (tmp_path / "runs").mkdir()
    (tmp_path / "tables" / "sessions").mkdir(parents=True)
    stale = [
        tmp_path / ".sessions.parquet.k2j3.tmp",
        tmp_path / "tables" / "sessions" / ".lot=L01.parquet.k2j3.tmp",
        tmp_path / "calibrations" / "U1" / ".20261122T000000.000000Z.json.ab12.tmp",
        tmp_path / "runs" / ".r1.json.zz.tmp",
    ]
    keep = [
        tmp_path / "sessions.parquet",
        tmp_path / "notes.tmp.txt",
        tmp_path / "tables" / "sessions" / "lot=L01.parquet",
    ]
    for p in stale + keep:
        p.write_bytes(b"partial")
    with store.lock(owner="holder"):
        assert all(not p.exists() for p in stale)
        # the holder's own write in progress: a refused second run must not touch it
        in_progress = tmp_path / "tables" / "sessions" / ".lot=L02.parquet.x1y2.tmp"
        in_progress.write_bytes(b"being written")
        with pytest.raises(StoreLockedError):
            with ResultsStore(tmp_path).lock(owner="second"):
                pass
        assert in_progress.exists()
        in_progress.unlink()
    assert all(p.exists() for p in keep)
