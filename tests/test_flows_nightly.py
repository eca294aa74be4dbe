"""The nightly flow end to end on simulated files, incremental runs, rerun, Dask, lock, apply.

One temporary local Prefect API serves the whole module (PREFECT_HOME in a temp dir, set by
flows.runtime before Prefect is imported)."""

from __future__ import annotations

import os
import shutil
from pathlib import Path

import numpy as np
import pandas as pd
import pyarrow.parquet as pq
import pytest

from flows import runtime

runtime.ensure_environment()

from flows import fleet_sim  # noqa: E402
from flows.cli import main as cli_main  # noqa: E402
from flows.fleet_sim import simulate_fleet  # noqa: E402
from flows.nightly import FLOW_PRELOAD, nightly_fleet_calibration, rerun_unit  # noqa: E402
from schemas.results_store import ResultsStore, StoreLockedError, find_calibration  # noqa: E402

RATE_HZ = 20.0
# outliers far beyond the lot spread (20 lot sd): the flag rule controls the chance of a false
# flag over the whole fleet at 1 %, which costs power near 6-7 sd (docs/flows.md)
BIG_OUTLIERS = (("k_g11", "K_g", (0, 0), 0.06), ("w0_z", "w0", (2,), 1.0), ("k_a22", "K_a", (1, 1), 0.06))


def temp_files(root: Path) -> list[Path]:
    return [p for p in root.rglob("*") if p.name.endswith(".tmp")]


def table(results: Path, name: str) -> pd.DataFrame:
    return ResultsStore(results).read(name)


def lot_files(results: Path) -> dict[tuple[str, str], tuple[int, int]]:
    """(table, lot) -> (inode, mtime_ns) of every lot file of the store: a rewrite (temp file
    + os.replace) changes the inode."""
    store = ResultsStore(results)
    out = {}
    for name in (
        "sessions",
        "parameters",
        "summary",
        "units",
        "residuals",
        "compensation",
        "discovery",
        "navigation",
    ):
        for lot, path in store.partitions(name).items():
            st = path.stat()
            out[(name, lot)] = (st.st_ino, st.st_mtime_ns)
    return out


def unit_rows(df: pd.DataFrame, unit: str) -> pd.DataFrame:
    return df[df["unit"] == unit].reset_index(drop=True)


def other_rows(df: pd.DataFrame, unit: str) -> pd.DataFrame:
    return df[df["unit"] != unit].reset_index(drop=True)


@pytest.fixture(scope="module")
def fleet(tmp_path_factory):
    """3 lots x 20 units x 5 reps, 2 outlier units, 3 bad sessions, first nightly run."""
    base = tmp_path_factory.mktemp("fleet")
    data, results = base / "data", base / "results"
    mp = pytest.MonkeyPatch()
    mp.setattr(fleet_sim, "OUTLIER_KINDS", BIG_OUTLIERS)
    manifest = simulate_fleet(
        data, lots=3, units=20, reps=5, seed=2026, sample_rate_hz=RATE_HZ, outliers=2, bad_sessions=3
    )
    mp.undo()
    log = nightly_fleet_calibration(data, results, run_discovery=False, progress=False)
    return data, results, manifest, log


@pytest.mark.slow
def test_fleet_run_flags_outliers_lists_bad_sessions_calibrates_the_rest(fleet):
    data, results, manifest, log = fleet
    outliers = {f"{o['lot']}/{o['unit']}" for o in manifest["outliers"]}
    assert len(outliers) == 2
    assert set(log["flagged_units"]) == outliers
    # the flag names the injected parameter
    flags = [f for lf in log["flags"] for f in lf["flags"]]
    for o in manifest["outliers"]:
        mine = [f for f in flags if f["unit"] == o["unit"]]
        assert any(f["parameter"] == o["param"] for f in mine), mine
    # bad sessions: exactly those, each with the expected code and a reason naming it
    bad = {b["session"]: b["expected_code"] for b in manifest["bad_sessions"]}
    failed = {f["session"]: f for f in log["failed_sessions"]}
    assert set(failed) == set(bad)
    for s, code in bad.items():
        assert failed[s]["code"] == code and s in failed[s]["message"]
    sessions = table(results, "sessions")
    assert len(sessions) == 300
    assert (sessions["status"] == "failed").sum() == 3
    # everything else calibrated: all 60 units (a unit with one bad session keeps 4 reps)
    units = table(results, "units")
    assert len(units) == 60 and set(units["state"]) == {"calibrated"}
    assert {f"{r.lot}/{r.unit}" for r in units.itertuples() if r.flagged} == outliers
    summary = table(results, "summary")
    assert summary.groupby("unit")["flagged"].any().sum() == 2
    for u in units["unit"]:
        assert find_calibration(results, u).exists()
    params = table(results, "parameters")
    assert params.groupby(["lot", "unit", "rep"]).ngroups == 297
    assert log["summary"].startswith("nightly ") and "flagged units:" in log["summary"]
    assert temp_files(results) == []
    # the lot reports were written
    assert log["reports"] and all(Path(p).exists() for p in log["reports"])
    # the numerics and report modules were imported while Prefect started, all of them
    assert log["preload"]["modules"] == len(FLOW_PRELOAD) and "failed" not in log["preload"]


@pytest.mark.slow
def test_second_run_recalibrates_nothing_then_one_changed_session_one_unit(fleet):
    data, results, manifest, first = fleet
    params_before = table(results, "parameters")
    files_before = sorted((results / "calibrations").rglob("*.json"))
    log = nightly_fleet_calibration(data, results, run_discovery=False, progress=False)
    assert log["units_calibrated"] == 0 and log["units_skipped"] == 60
    pd.testing.assert_frame_equal(table(results, "parameters"), params_before)
    assert sorted((results / "calibrations").rglob("*.json")) == files_before

    target = data / "lot=L02" / "unit=U0025" / "rep=3" / "samples.parquet"
    st = target.stat()
    os.utime(target, ns=(st.st_atime_ns, st.st_mtime_ns + 10_000_000_000))
    log = nightly_fleet_calibration(data, results, run_discovery=False, progress=False)
    assert log["units_calibrated"] == 0  # touched, same content: a content fingerprint
    # the same samples written again with one more metadata entry: other bytes
    tab = pq.read_table(target)
    pq.write_table(tab.replace_schema_metadata({**tab.schema.metadata, b"operator": b"x"}), target)
    files_before = lot_files(results)
    log = nightly_fleet_calibration(data, results, run_discovery=False, progress=False)
    assert log["units_calibrated"] == 1 and log["units_skipped"] == 59
    files_after = lot_files(results)
    assert {k: v for k, v in files_after.items() if k[1] != "L02"} == {
        k: v for k, v in files_before.items() if k[1] != "L02"
    }
    assert files_after[("parameters", "L02")] != files_before[("parameters", "L02")]
    after = table(results, "parameters")
    pd.testing.assert_frame_equal(other_rows(after, "U0025"), other_rows(params_before, "U0025"))
    assert set(unit_rows(after, "U0025")["run_id"]) == {log["run_id"]}
    assert len(sorted((results / "calibrations" / "U0025").glob("*.json"))) == 2


@pytest.mark.slow
def test_rerun_changes_only_that_unit_and_a_failed_rerun_keeps_the_last_good(fleet):
    data, results, manifest, _ = fleet
    tables = {n: table(results, n) for n in ("parameters", "summary", "sessions", "residuals")}
    cal_before = find_calibration(results, "U0007")
    files_before = lot_files(results)
    log = rerun_unit(data, results, "U0007", run_discovery=False)
    assert log["units_calibrated"] == 1 and not log["units_failed"]
    # the store is partitioned by lot: the rerun of a unit of L01 rewrote L01's files only (the
    # other lots' flags did not move: their values are the same and so is the pooled scale)
    files_after = lot_files(results)
    assert {k: v for k, v in files_after.items() if k[1] != "L01"} == {
        k: v for k, v in files_before.items() if k[1] != "L01"
    }
    assert files_after[("residuals", "L01")] != files_before[("residuals", "L01")]
    assert set(log["phases_s"]) == {"calibrate", "store", "reflag", "reports"}
    for name, before in tables.items():
        after = table(results, name)
        pd.testing.assert_frame_equal(
            other_rows(after, "U0007"), other_rows(before, "U0007"), check_dtype=False
        )
    assert set(unit_rows(table(results, "parameters"), "U0007")["run_id"]) == {log["run_id"]}
    cal_new = find_calibration(results, "U0007")
    assert cal_new != cal_before and cal_before.exists()
    # the rerun writes the unit report with the zhang2017 navigation drift of the unit's model
    nav = unit_rows(table(results, "navigation"), "U0007")
    assert set(nav["case"]) == {"none", "static", "static+dynamic"}
    final = nav[nav["t"] == nav["t"].max()].set_index("case")
    assert final.loc["static+dynamic", "vel_err"] < 1e-6 < final.loc["none", "vel_err"]
    assert (results / "reports" / "units" / "U0007.html").exists()

    # damage every session of U0007: the rerun fails, the last good calibration stays
    good_params = unit_rows(table(results, "parameters"), "U0007")
    for rep in (data / "lot=L01" / "unit=U0007").glob("rep=*"):
        shutil.move(rep / "steps.parquet", rep / "steps.parquet.bak")
    try:
        assert (
            cli_main(["rerun", str(data), "--results", str(results), "--unit", "U0007", "--no-discovery"])
            == 1
        )
    finally:
        for rep in (data / "lot=L01" / "unit=U0007").glob("rep=*"):
            shutil.move(rep / "steps.parquet.bak", rep / "steps.parquet")
    pd.testing.assert_frame_equal(unit_rows(table(results, "parameters"), "U0007"), good_params)
    assert find_calibration(results, "U0007") == cal_new
    units = table(results, "units").set_index("unit")
    assert units.loc["U0007", "state"] == "stale"
    assert "E_MISSING_FILE" in units.loc["U0007", "reason"]
    summ = unit_rows(table(results, "summary"), "U0007")
    assert summ["stale"].all() and summ["stale_reason"].str.contains("recalibration failed").all()
    sess = unit_rows(table(results, "sessions"), "U0007")
    assert (sess["status"] == "failed").all() and (sess["error_code"] == "E_MISSING_FILE").all()
    assert temp_files(results) == []


# --- small fleet: Dask, discovery, lock, apply --------------------------------------------------
@pytest.fixture(scope="module")
def small(tmp_path_factory):
    base = tmp_path_factory.mktemp("small")
    data = base / "data"
    manifest = simulate_fleet(data, lots=1, units=5, reps=2, seed=7, sample_rate_hz=RATE_HZ, bad_sessions=1)
    return data, base, manifest


@pytest.mark.slow
def test_dask_local_cluster_gives_the_same_results(small):
    from distributed import LocalCluster

    data, base, manifest = small
    log_t = nightly_fleet_calibration(data, base / "r_threads", progress=False, batch_size=2)
    with LocalCluster(n_workers=2, threads_per_worker=1, processes=False, dashboard_address=":0") as cluster:
        log_d = nightly_fleet_calibration(
            data, base / "r_dask", progress=False, batch_size=2, dask_address=cluster.scheduler_address
        )
    assert log_t["units_calibrated"] == log_d["units_calibrated"] == 5
    for name in ("parameters", "summary", "sessions", "discovery"):
        a = table(base / "r_threads", name).drop(columns=["run_id", "calibrated_at"], errors="ignore")
        b = table(base / "r_dask", name).drop(columns=["run_id", "calibrated_at"], errors="ignore")
        pd.testing.assert_frame_equal(a, b)
    # Prefect persisted no task results (no sample data, no fitted arrays) under its home
    home = Path(os.environ["PREFECT_HOME"])
    stored = [p for p in (home / "storage").rglob("*") if p.is_file()] if (home / "storage").exists() else []
    assert stored == []
    assert (
        [f["session"] for f in log_t["failed_sessions"]]
        == [f["session"] for f in log_d["failed_sessions"]]
        == [b["session"] for b in manifest["bad_sessions"]]
    )


@pytest.mark.slow
def test_worker_processes_give_the_same_results_as_threads(small):
    """runner=processes (flows.compute_pool: a forkserver pool doing the unit work) stores
    exactly what the thread pool stores; the run log says where the work ran."""
    data, base, manifest = small
    log_t = nightly_fleet_calibration(
        data, base / "r_threads2", progress=False, batch_size=2, runner="threads"
    )
    log_p = nightly_fleet_calibration(
        data, base / "r_procs", progress=False, batch_size=2, runner="processes"
    )
    assert log_t["unit_work"] == "task runner" and log_p["unit_work"] == "worker processes"
    assert log_t["units_calibrated"] == log_p["units_calibrated"] == 5
    for name in ("parameters", "summary", "sessions", "discovery", "residuals", "compensation"):
        a = table(base / "r_threads2", name).drop(columns=["run_id", "calibrated_at"], errors="ignore")
        b = table(base / "r_procs", name).drop(columns=["run_id", "calibrated_at"], errors="ignore")
        pd.testing.assert_frame_equal(a, b)


@pytest.mark.slow
def test_a_served_run_starts_the_workers_forkserver_itself(small, monkeypatch):
    """A served deployment calls the flow without nightly_fleet_calibration, which would have
    started the forkserver while Prefect started: the flow's body asks for it, before its
    first batch."""
    from flows import nightly

    data, base, _ = small
    calls: list[tuple] = []
    monkeypatch.setattr(
        nightly, "prestart_unit_work_pool", lambda kind, dataset: calls.append((kind, str(dataset)))
    )
    with runtime.run_settings():
        log = nightly.nightly_flow(
            str(data), str(base / "r_served"), progress=False, runner="threads", run_discovery=False
        )
    assert calls == [("threads", str(data))] and log["units_calibrated"] == 5


def test_second_concurrent_run_is_refused(small, capsys):
    data, base, _ = small
    results = base / "r_lock"
    with ResultsStore(results).lock(owner="other-run"):
        with pytest.raises(StoreLockedError, match="other-run"):
            nightly_fleet_calibration(data, results, progress=False, run_discovery=False)
        assert cli_main(["nightly", str(data), "--results", str(results), "--quiet", "--no-discovery"]) == 2
        assert "in use by run other-run" in capsys.readouterr().err
    assert not ResultsStore(results).exists() and not (results / "tables").exists()


def test_nightly_command_prints_failures_summary_and_reports(small, capsys):
    data, base, manifest = small
    results = base / "r_cli"
    # exit code 1: a session failed (README, exit codes)
    assert (
        cli_main(["nightly", str(data), "--results", str(results), "--no-discovery", "--batch-size", "2"])
        == 1
    )
    out, err = capsys.readouterr()
    bad = manifest["bad_sessions"][0]["session"]
    assert f"failed session {bad}: [" in err
    # one line per lot as its batches (of 2 units) come back, the last one 5/5 units
    import re

    counts = [int(m) for m in re.findall(r"^lot L\w+: (\d)/5 units", err, re.M)]
    assert counts == sorted(counts) and counts[-1] == 5 and len(counts) == 3
    assert re.search(r"^lot L\w+: 5/5 units \(1 failed sessions\), [\d.]+ s$", err, re.M)
    # the summary's time is the wall time since the process started, the flow's in brackets
    assert re.search(r"; [\d.]+ s wall \([\d.]+ s in the flow\)$", out, re.M)
    summary = [line for line in out.splitlines() if line.startswith("nightly ")]
    assert len(summary) == 1 and "5 units (5 calibrated, 0 unchanged" in summary[0]
    assert "reports: " in out
    run_logs = list((results / "runs").glob("*.json"))
    assert len(run_logs) == 1
    import json

    log = json.loads(run_logs[0].read_text())
    assert log["progress"]["units_done"] == 5 and log["end"] >= log["start"]


def test_report_command_rebuilds_the_lot_report(small, capsys):
    data, base, _ = small
    results = base / "r_threads"
    if not ResultsStore(results).has_table("summary"):
        nightly_fleet_calibration(data, results, progress=False)
    assert cli_main(["report", "--results", str(results), "--lot", "L01"]) == 0
    out = capsys.readouterr().out
    assert "fewer than 5" not in out and "L01" in out
    assert cli_main(["report", "--results", str(results), "--lot", "NOPE"]) == 2


def _step_means(df: pd.DataFrame, cols) -> pd.DataFrame:
    return df[df["step"] >= 0].groupby("step")[list(cols)].mean()


def test_apply_calibrates_raw_samples_and_refuses_unit_mismatch(small, tmp_path, capsys):
    data, base, manifest = small
    results = base / "r_threads"
    if not ResultsStore(results).has_table("summary"):
        nightly_fleet_calibration(data, results, progress=False)
    unit = manifest["units"][1]
    cal = find_calibration(results, unit["unit"])
    samples = data / "lot=L01" / f"unit={unit['unit']}" / "rep=1" / "samples.parquet"
    steps = pd.read_parquet(samples.parent / "steps.parquet").set_index("step")
    out = tmp_path / "cal.parquet"
    assert cli_main(["apply", str(cal), str(samples), str(out)]) == 0
    res = pq.read_table(out)
    assert res.schema.metadata[b"gyro_unit"] == b"deg/s"
    df = res.to_pandas()
    means = _step_means(df, ["w_x", "w_y", "w_z", "f_x", "f_y", "f_z"])
    raw = _step_means(pd.read_parquet(samples), ["gx", "gy", "gz", "ax", "ay", "az"])
    ref_w = steps.loc[means.index, ["w_ref_x", "w_ref_y", "w_ref_z"]].to_numpy()
    ref_f = steps.loc[means.index, ["f_ref_x", "f_ref_y", "f_ref_z"]].to_numpy()
    err_cal = np.abs(means[["w_x", "w_y", "w_z"]].to_numpy() - ref_w)
    err_raw = np.abs(raw[["gx", "gy", "gz"]].to_numpy() - ref_w)
    # truth: 1 % scale/cross-axis errors, 0.5 deg/s biases -> raw errors of several deg/s at
    # 300 deg/s; calibrated: noise (0.05 deg/s white over ~50 samples) + bias instability
    assert np.median(err_raw) > 0.1 and err_raw.max() > 2.0
    assert np.median(err_cal) < 0.05 and err_cal.max() < 0.5
    static = (steps.loc[means.index, "rate_dps"] == 0).to_numpy()
    err_f = np.abs(means[["f_x", "f_y", "f_z"]].to_numpy() - ref_f)[static]
    assert err_f.max() < 2e-3  # 1 mg white noise over ~50 samples + 0.05 mg instability

    # CSV: acc in m/s^2, gyr in deg/s -> the same numbers
    s = pd.read_parquet(samples)
    g_local = float(pq.read_schema(samples).metadata[b"g_local"])
    csv = pd.DataFrame(
        {
            "t": s["t"],
            "acc_x": s["ax"] * g_local,
            "acc_y": s["ay"] * g_local,
            "acc_z": s["az"] * g_local,
            "gyr_x": s["gx"],
            "gyr_y": s["gy"],
            "gyr_z": s["gz"],
        }
    )
    csv.to_csv(tmp_path / "raw.csv", index=False)
    assert cli_main(["apply", str(cal), str(tmp_path / "raw.csv"), str(tmp_path / "o.csv")]) == 0
    o = pd.read_csv(tmp_path / "o.csv")
    from schemas.calibration_file import load_calibration

    gl = load_calibration(cal).g_local
    np.testing.assert_allclose(
        o[["gyr_x", "gyr_y", "gyr_z"]].to_numpy(), df[["w_x", "w_y", "w_z"]].to_numpy(), atol=2e-3
    )
    np.testing.assert_allclose(
        o[["acc_x", "acc_y", "acc_z"]].to_numpy() / gl, df[["f_x", "f_y", "f_z"]].to_numpy(), atol=2e-4
    )
    # LSB data with a deg/s calibration: refused
    assert (
        cli_main(
            ["apply", str(cal), str(tmp_path / "raw.csv"), str(tmp_path / "x.csv"), "--gyro-unit", "LSB"]
        )
        == 2
    )
    err = capsys.readouterr().err
    assert "do not match the calibration's raw_units" in err
    assert not (tmp_path / "x.csv").exists()


@pytest.mark.parametrize("command", ["nightly", "report", "rerun", "serve", "calibration", "apply"])
def test_every_command_has_help(command, capsys):
    with pytest.raises(SystemExit) as exc:
        cli_main([command, "--help"])
    assert exc.value.code == 0
    assert "examples:" in capsys.readouterr().out
