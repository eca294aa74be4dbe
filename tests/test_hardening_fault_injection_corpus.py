"""Fault-injection corpus of the second hardening round (issue 19, issue 17 item 4).

Each case: the damage done, the expected code and message, the exit code, and the store's
state after the run and after the next run. The cases that need a nightly run share one
temporary Prefect API (module scope) and are marked slow; the rest run without Prefect."""

from __future__ import annotations

import errno
import json
import os
import shutil
from pathlib import Path

import numpy as np
import pandas as pd
import pyarrow as pa
import pyarrow.dataset as pads
import pyarrow.parquet as pq
import pytest

from flows import runtime

runtime.ensure_environment()

from calib_core.calibration import Calibration, TermValue  # noqa: E402
from calib_core.effects import get_effect  # noqa: E402
from calib_core.sim import protocols  # noqa: E402
from calib_core.sim.simulator import typical_truth  # noqa: E402
from flows import fleet_sim, nightly, unit_pipeline  # noqa: E402
from flows.cli import main as cli_main  # noqa: E402
from flows.fleet_sim import simulate_fleet  # noqa: E402
from flows.unit_pipeline import UnitJob, calibrate_batch  # noqa: E402
from schemas import errors as E  # noqa: E402
from schemas.averaging import read_step_means  # noqa: E402
from schemas.calibration_file import load_calibration, save_calibration  # noqa: E402
from schemas.dataset import check_id, find_sessions, id_problem  # noqa: E402
from schemas.errors import SessionError  # noqa: E402
from schemas.reader import session_from_tables  # noqa: E402
from schemas.results_store import ResultsStore, StoreError  # noqa: E402
from schemas.store_tables import TABLE_SCHEMAS  # noqa: E402

RATE_HZ = 20.0


def calibration_files(results: Path) -> set[Path]:
    return set((results / "calibrations").rglob("*.json"))


def one_line_error(capsys, command: str) -> str:
    err = capsys.readouterr().err.strip().splitlines()
    mine = [line for line in err if line.startswith(f"mimucal {command}: error:")]
    assert len(mine) == 1, err
    assert "Traceback" not in "\n".join(err)
    return mine[0]


# --- names -----------------------------------------------------------------------------------
@pytest.mark.parametrize(
    "bad",
    [
        ".",
        "..",
        "U0001\n",
        "U\x00",
        "U\t1",
        "a/b",
        "-rf",
        "U1.",
        ".hidden",
        "CON",
        "nul.txt",
        "",
        "x" * 129,
        "U 7",
        "é",
    ],
)
def test_ids_are_full_string_matches(bad):
    assert id_problem(bad, "unit") is not None
    with pytest.raises(ValueError):
        check_id(bad, "unit")


def test_good_ids_pass():
    for good in ("U0001", "L01", "a.b-c_d", "x" * 128, "7"):
        assert check_id(good, "unit") == good


def test_directory_with_trailing_newline_is_a_bad_path(tmp_path):
    simulate_fleet(tmp_path / "d", 1, 1, 1, seed=1, sample_rate_hz=RATE_HZ)
    src = tmp_path / "d" / "lot=L01" / "unit=U0001"
    shutil.copytree(src, tmp_path / "d" / "lot=L01" / "unit=U0001\n")
    refs, errs = find_sessions(tmp_path / "d")
    assert [str(r.key) for r in refs] == ["lot=L01/unit=U0001/rep=1"]
    assert len(errs) == 1 and errs[0].code == E.E_BAD_PATH
    assert "must match" in str(errs[0])


@pytest.mark.parametrize(
    "argv",
    [
        ["calibration", "--results", "{r}", "--unit", "../../evil"],
        ["calibration", "--results", "{r}", "--unit", "."],
        ["report", "--results", "{r}", "--lot", ".."],
        ["rerun", "{r}", "--results", "{r}", "--unit", "U1\n"],
    ],
)
def test_unit_and_lot_arguments_go_through_the_name_check(tmp_path, capsys, argv):
    code = cli_main([a.format(r=tmp_path) for a in argv])
    assert code == 2
    line = one_line_error(capsys, argv[0])
    assert "must match" in line
    assert not any(tmp_path.iterdir())  # nothing written


def test_store_refuses_to_write_a_calibration_under_a_bad_unit_name(tmp_path):
    cal = Calibration(np.eye(3), np.zeros(3), np.eye(3), np.zeros(3))
    with pytest.raises(ValueError):
        ResultsStore(tmp_path).save_calibration(cal, "..", {})
    assert not (tmp_path / "calibrations").exists() or not any(tmp_path.rglob("*.json"))


# --- symbolic links ------------------------------------------------------------------------------
def test_lock_that_is_a_symlink_is_refused_and_its_target_untouched(tmp_path):
    victim = tmp_path / "victim.txt"
    victim.write_text("precious")
    results = tmp_path / "results"
    results.mkdir()
    (results / ".lock").symlink_to(victim)
    with pytest.raises(StoreError, match="symbolic link"):
        with ResultsStore(results).lock("test"):
            pass
    assert victim.read_text() == "precious"


def test_symlink_under_results_is_refused_by_the_check(tmp_path):
    results = tmp_path / "results"
    (results / "tables").mkdir(parents=True)
    outside = tmp_path / "elsewhere"
    outside.mkdir()
    (results / "runs").symlink_to(outside)
    problems = ResultsStore(results).verify()
    assert len(problems) == 1 and "runs is a symbolic link" in problems[0]
    with pytest.raises(StoreError, match="symbolic link"):
        ResultsStore(results).check()


def test_session_reached_through_a_symlink(tmp_path):
    """The dataset's one link rule: any link refused without --follow-symlinks; with it, a
    link inside the dataset root is followed, one leading outside never."""
    simulate_fleet(tmp_path / "other", 1, 1, 1, seed=2, sample_rate_hz=RATE_HZ)
    data = tmp_path / "data"
    (data / "lot=L01").mkdir(parents=True)
    (data / "lot=L01" / "unit=U0009").symlink_to(tmp_path / "other" / "lot=L01" / "unit=U0001")
    for follow in (False, True):
        refs, errs = find_sessions(data, follow_symlinks=follow)
        assert refs == [] and len(errs) == 1 and errs[0].code == E.E_BAD_PATH
        assert ("outside the dataset root" in str(errs[0])) == follow, str(errs[0])
        assert ("--follow-symlinks" in str(errs[0])) != follow, str(errs[0])
    # a link inside the dataset root: refused without the flag, followed (resolved) with it
    (data / "lot=L01" / "unit=U0009").unlink()
    shutil.copytree(tmp_path / "other" / "lot=L01" / "unit=U0001", data / "_real")
    (data / "lot=L01" / "unit=U0009").symlink_to(data / "_real")
    refs, errs = find_sessions(data)
    assert refs == [] and "symbolic link" in str(errs[0]) and "--follow-symlinks" in str(errs[0])
    refs, errs = find_sessions(data, follow_symlinks=True)
    assert errs == [] and refs[0].path == (data / "_real" / "rep=1").resolve()
    # a session file linked out of the dataset: never read, with or without the flag
    (data / "lot=L01" / "unit=U0009").unlink()
    shutil.copytree(data / "_real", data / "lot=L01" / "unit=U0009")
    samples = data / "lot=L01" / "unit=U0009" / "rep=1" / "samples.parquet"
    samples.unlink()
    samples.symlink_to(tmp_path / "other" / "lot=L01" / "unit=U0001" / "rep=1" / "samples.parquet")
    for follow in (False, True):
        refs, errs = find_sessions(data, follow_symlinks=follow)
        assert refs == [] and errs[0].code == E.E_BAD_PATH and "samples.parquet" in str(errs[0])


# --- data that is wrong although it decodes -----------------------------------------------------
@pytest.fixture(scope="module")
def one_session(tmp_path_factory):
    root = tmp_path_factory.mktemp("one")
    simulate_fleet(root, 1, 1, 1, seed=11, sample_rate_hz=RATE_HZ)
    ref = find_sessions(root)[0][0]
    return ref, pq.read_table(ref.steps_path), pq.read_table(ref.samples_path)


def test_step_id_reappearing_after_another_step_is_an_error(one_session):
    ref, steps, samples = one_session
    ids = samples.column("step").to_numpy().copy()
    rows_3 = np.flatnonzero(ids == 3)
    ids[rows_3[-10:]] = 4  # the end of step 3 labelled 4, then step 3 again? no: 3 -> 4 -> 4
    ids[np.flatnonzero(ids == 5)[:10]] = 3  # step 3 reappears after step 4's samples
    table = samples.set_column(samples.schema.get_field_index("step"), "step", pa.array(ids, pa.int32()))
    with pytest.raises(SessionError) as info:
        session_from_tables(ref.key, steps, table, samples.schema.metadata)
    assert info.value.code == E.E_STEP_NOT_CONTIGUOUS
    assert "step 3 are not one run in time" in str(info.value)
    # samples of no step (-1) inside a step do not split it into two steps
    ids = samples.column("step").to_numpy().copy()
    ids[np.flatnonzero(ids == 3)[5:8]] = -1
    table = samples.set_column(samples.schema.get_field_index("step"), "step", pa.array(ids, pa.int32()))
    session_from_tables(ref.key, steps, table, samples.schema.metadata)


def _relabel_steps(ref, samples: pa.Table, n: int, out: Path) -> Path:
    """A copy of the session whose first ``n`` steps' samples are relabelled -1 (each step
    then has no samples: W_EMPTY_STEP), written without checksums (still decodes)."""
    out.mkdir(parents=True, exist_ok=True)
    shutil.copy(ref.steps_path, out / "steps.parquet")
    ids = samples.column("step").to_numpy().copy()
    ids[ids < n] = -1
    table = samples.set_column(samples.schema.get_field_index("step"), "step", pa.array(ids, pa.int32()))
    pq.write_table(table, out / "samples.parquet")
    return out


def test_session_losing_more_than_five_percent_of_its_steps_fails(one_session, tmp_path, monkeypatch):
    from schemas.dataset import SessionRef

    ref, steps, samples = one_session
    n_steps = steps.num_rows  # 118
    ok = SessionRef(ref.key, _relabel_steps(ref, samples, 5, tmp_path / "five"))  # 4.2 %
    sm, warns = read_step_means(ok)
    assert [w.code for w in warns] == [E.W_EMPTY_STEP] * 5 and len(sm.step) == n_steps - 5
    bad = SessionRef(ref.key, _relabel_steps(ref, samples, 16, tmp_path / "sixteen"))  # 13.6 %
    with pytest.raises(SessionError) as info:
        read_step_means(bad)
    assert info.value.code == E.E_TOO_MANY_STEPS_LOST
    assert f"16 of {n_steps} steps left out (16 W_EMPTY_STEP), more than the 5% allowed" in str(info.value)
    monkeypatch.setenv("MIMUCAL_MAX_LOST_STEP_SHARE", "0.2")  # configurable
    read_step_means(bad)


def _chunks(path: Path) -> list[tuple[str, int, int]]:
    md = pq.ParquetFile(path).metadata
    return [
        (
            md.row_group(g).column(c).path_in_schema,
            md.row_group(g).column(c).data_page_offset,
            md.row_group(g).column(c).total_compressed_size,
        )
        for g in range(md.num_row_groups)
        for c in range(md.num_columns)
    ]


def _damaged(original: bytes, start: int, size: int, how: str) -> bytes:
    b = bytearray(original)
    if how == "flip":  # a few bits: the page still decompresses and decodes
        for p in start + size // 2 + np.arange(4):
            b[p] ^= 0x5A
    else:  # 16 zero bytes: usually no longer decodes
        b[start + size // 3 : start + size // 3 + 16] = bytes(16)
    return bytes(b)


def test_damaged_bytes_in_each_column_chunk_are_never_calibrated(one_session, tmp_path):
    """Every column chunk of a simulated samples file, damaged in two ways: the session is
    rejected each time (E_CHECKSUM, or E_UNREADABLE_FILE where the bytes do not decode), and
    the unit pipeline marks it failed, never warned or ok."""
    from schemas.dataset import SessionRef

    ref, _, _ = one_session
    work = tmp_path / "s"
    shutil.copytree(ref.path, work)
    session = SessionRef(ref.key, work)
    original = (ref.path / "samples.parquet").read_bytes()
    chunks = _chunks(ref.samples_path)
    assert [c[0] for c in chunks] == ["step", "t", "gx", "gy", "gz", "ax", "ay", "az"]
    codes = {}
    for name, start, size in chunks:
        for how in ("flip", "zero"):
            session.samples_path.write_bytes(_damaged(original, start, size, how))
            out = unit_pipeline.calibrate_session(session)
            assert out.status == "failed", (name, how, out.warnings)
            codes[(name, how)] = out.code
    assert set(codes.values()) <= {E.E_CHECKSUM, E.E_UNREADABLE_FILE}
    assert E.E_CHECKSUM in set(codes.values())


def test_without_checksums_damaged_step_and_time_columns_are_still_caught(one_session, tmp_path):
    """A file written without page checksums (another writer): damage to the step and time
    columns that still decodes is caught by the content rules (unknown or reappearing step
    ids, too many steps lost, non-increasing time). Damage to a sensor column that still
    decodes is not caught unless it makes a value non-finite (docs/hardening.md)."""
    from schemas.dataset import SessionRef

    ref, _, samples = one_session
    work = tmp_path / "s"
    shutil.copytree(ref.path, work)
    pq.write_table(samples, work / "samples.parquet", compression="zstd", use_dictionary=False)
    original = (work / "samples.parquet").read_bytes()
    session = SessionRef(ref.key, work)
    for name, start, size in _chunks(work / "samples.parquet")[:2]:
        for how in ("flip", "zero"):
            session.samples_path.write_bytes(_damaged(original, start, size, how))
            out = unit_pipeline.calibrate_session(session)
            assert out.status == "failed", (name, how)
            assert out.code in {
                E.E_UNKNOWN_STEP,
                E.E_STEP_NOT_CONTIGUOUS,
                E.E_UNREADABLE_FILE,
                E.E_TOO_MANY_STEPS_LOST,
                E.E_NONINCREASING_TIME,
            }, out.code


# --- calibration files: non-finite numbers ------------------------------------------------------
def test_nonfinite_term_values_are_written_as_null_and_read_back_as_nan(tmp_path):
    lever = get_effect("lever_arm")
    params = np.arange(9, dtype=float)
    stderr = np.full(9, 0.1)
    params[4], stderr[[4, 5]] = np.nan, np.nan
    cal = Calibration(
        np.eye(3), np.zeros(3), np.eye(3), np.zeros(3), terms=(TermValue("lever_arm", params, stderr),)
    )
    path = save_calibration(cal, tmp_path / "c.json", {"x": {"y": float("inf")}})
    doc = json.loads(path.read_text(), parse_constant=lambda c: pytest.fail(f"{c} written"))
    assert doc["terms"][0]["params"][lever.param_names[4]] is None
    assert doc["terms"][0]["stderr"][lever.param_names[5]] is None
    assert doc["x"]["y"] is None
    back = load_calibration(path)
    np.testing.assert_array_equal(np.isnan(back.terms[0].params), np.isnan(params))
    with pytest.raises(ValueError, match="not finite"):
        save_calibration(
            Calibration(np.full((3, 3), np.nan), np.zeros(3), np.eye(3), np.zeros(3)), tmp_path / "bad.json"
        )
    assert not (tmp_path / "bad.json").exists()


# --- one unit never fails the flow (without Prefect) ----------------------------------------------
@pytest.fixture(scope="module")
def small_fleet(tmp_path_factory):
    root = tmp_path_factory.mktemp("small")
    simulate_fleet(root, 1, 3, 2, seed=21, sample_rate_hz=RATE_HZ)
    refs, _ = find_sessions(root)
    jobs = {}
    for r in refs:
        jobs.setdefault(r.key.unit, []).append(r)
    return root, [UnitJob("L01", u, rs, "new") for u, rs in sorted(jobs.items())]


def test_an_exception_in_one_units_calibration_fails_that_unit_only(small_fleet, monkeypatch):
    _, jobs = small_fleet
    real = unit_pipeline.calibrate_unit_job

    def broken(job, run_discovery=True):
        if job.unit == "U0002":
            raise ZeroDivisionError("injected")
        return real(job, run_discovery)

    monkeypatch.setitem(unit_pipeline.UNIT_PIPELINES, "turntable", broken)  # the kind's pipeline
    res = calibrate_batch(jobs, run_discovery=False)
    assert [r.calibrated for r in res] == [True, False, True]
    assert res[1].error_code == "E_INTERNAL"
    assert res[1].error == (
        "[E_INTERNAL] unit L01/U0002: unexpected error while calibrating (ZeroDivisionError: injected)"
    )


def test_an_exception_while_storing_one_unit_keeps_its_last_good_calibration(
    small_fleet, tmp_path, monkeypatch
):
    _, jobs = small_fleet
    store = ResultsStore(tmp_path)
    first = nightly.store_results(store, calibrate_batch(jobs, False), "run1", "v")
    assert first["calibrated"] == ["L01/U0001", "L01/U0002", "L01/U0003"]
    before = calibration_files(tmp_path)
    real = ResultsStore.save_calibration

    def broken(self, cal, unit, *a, **k):
        if unit == "U0003":
            raise ValueError("Out of range float values are not JSON compliant")
        return real(self, cal, unit, *a, **k)

    monkeypatch.setattr(ResultsStore, "save_calibration", broken)
    results = calibrate_batch(jobs, False)
    second = nightly.store_results(store, results, "run2", "v")
    assert second["calibrated"] == ["L01/U0001", "L01/U0002"]
    assert list(second["stale"]) == ["L01/U0003"]
    assert results[2].error_code == "E_INTERNAL" and "while storing its results" in results[2].error
    units = store.read("units").set_index("unit")
    assert units.loc["U0003", "state"] == "stale" and units.loc["U0003", "error_code"] == "E_INTERNAL"
    assert units.loc["U0003", "calibration_file"] in {str(p.relative_to(tmp_path)) for p in before}
    # no fingerprint for the failed unit: the next run tries it again
    sessions = store.read("sessions")
    assert sessions[sessions["unit"] == "U0003"]["fingerprint"].isna().all()
    jobs_next, skipped = nightly.plan_units([r for j in jobs for r in j.refs], store.fingerprints())
    assert [j.unit for j in jobs_next] == ["U0003"] and len(skipped) == 2


def test_a_failed_table_write_leaves_no_new_calibration_file(small_fleet, tmp_path, monkeypatch):
    _, jobs = small_fleet
    store = ResultsStore(tmp_path)
    nightly.store_results(store, calibrate_batch(jobs, False), "run1", "v")
    before = calibration_files(tmp_path)
    tables_before = {p: p.read_bytes() for p in (tmp_path / "tables").rglob("*.parquet")}
    import schemas.store_io as io

    def full(*a, **k):
        raise OSError(errno.ENOSPC, "No space left on device", str(tmp_path / "tables"))

    monkeypatch.setattr(io, "write_table_atomic", full)
    with pytest.raises(OSError):
        nightly.store_results(store, calibrate_batch(jobs, False), "run2", "v")
    assert calibration_files(tmp_path) == before
    assert {p: p.read_bytes() for p in (tmp_path / "tables").rglob("*.parquet")} == tables_before


# --- the store checks itself ------------------------------------------------------------------
def test_check_names_a_truncated_table_and_a_missing_calibration(small_fleet, tmp_path):
    _, jobs = small_fleet
    store = ResultsStore(tmp_path)
    nightly.store_results(store, calibrate_batch(jobs, False), "run1", "v")
    assert store.verify() == []
    part = store.partition_path("parameters", "L01")
    os.truncate(part, 100)
    cal = tmp_path / store.read("units")["calibration_file"].iloc[0]
    cal.unlink()
    problems = store.verify()
    assert len(problems) == 2
    assert problems[0].startswith(f"table parameters: {part} is damaged (ArrowInvalid")
    assert problems[0].endswith(f"run 'mimucal repair --results {tmp_path}' to rebuild what can be rebuilt")
    assert problems[1] == (
        f"unit L01/U0001: its current calibration file {cal} is missing; "
        f"run 'mimucal repair --results {tmp_path}' to rebuild what can be "
        f"rebuilt"
    )


def test_older_lot_files_are_rewritten_with_the_declared_schema(tmp_path):
    store = ResultsStore(tmp_path)
    d = tmp_path / "tables" / "summary"
    d.mkdir(parents=True)
    old = pd.DataFrame(
        {
            "lot": ["L01"],
            "unit": ["U1"],
            "model": ["gyro"],
            "parameter": ["k"],
            "mean": [1.0],
            "score": [None],
        }
    )  # score all null: Arrow null type
    pq.write_table(pa.Table.from_pandas(old, preserve_index=False), d / "lot=L01.parquet")
    assert pa.types.is_null(pq.read_schema(d / "lot=L01.parquet").field("score").type)
    store.write("units", pd.DataFrame({"lot": ["L01"], "unit": ["U1"], "state": ["calibrated"]}))
    assert pq.read_schema(d / "lot=L01.parquet").field("score").type == pa.float64()
    assert store.read("summary")["mean"].tolist() == [1.0]


# --- CLI: one line per failure -------------------------------------------------------------------
def test_an_unexpected_failure_is_one_line_and_debug_shows_the_traceback(tmp_path, capsys, monkeypatch):
    simulate_fleet(tmp_path / "d", 1, 1, 1, seed=3, sample_rate_hz=RATE_HZ)

    def prefect_down(*a, **k):
        raise RuntimeError("Prefect API at http://127.0.0.1:4200 is unreachable\nmore lines")

    monkeypatch.setattr(nightly, "nightly_fleet_calibration", prefect_down)
    argv = ["nightly", str(tmp_path / "d"), "--results", str(tmp_path / "r"), "--quiet"]
    assert cli_main(argv) == 5  # the run failed unexpectedly: not "some units failed" (1)
    line = one_line_error(capsys, "nightly")
    assert line.startswith("mimucal nightly: error: the run failed: RuntimeError: Prefect API")
    assert "more lines" not in line
    with pytest.raises(RuntimeError):
        cli_main(argv + ["--debug"])


def test_disk_full_and_read_only_are_one_line(tmp_path, capsys, monkeypatch):
    simulate_fleet(tmp_path / "d", 1, 1, 1, seed=3, sample_rate_hz=RATE_HZ)
    for err, words in (
        (errno.ENOSPC, "No space left on device (ENOSPC); free space"),
        (errno.EROFS, "Read-only file system (EROFS); the file system is read-only"),
    ):

        def fail(*a, _e=err, **k):
            raise OSError(_e, os.strerror(_e), str(tmp_path / "r" / "runs"))

        monkeypatch.setattr(nightly, "nightly_fleet_calibration", fail)
        assert cli_main(["nightly", str(tmp_path / "d"), "--results", str(tmp_path / "r")]) == 2
        line = one_line_error(capsys, "nightly")
        assert f"cannot write or read {tmp_path / 'r' / 'runs'}: " in line and words in line


# --- end to end through the nightly flow (one temporary Prefect API for these) ------------------
BIG_OUTLIERS = (("k_g11", "K_g", (0, 0), 0.15),)


@pytest.fixture(scope="module")
def lever_lot(tmp_path_factory):
    """1 lot x 10 units x 3 reps, every unit with lever arms of 4-12 mm on a protocol
    without tilted dynamic steps (six lever-arm components unobservable), one outlier unit,
    one bad session; first nightly run through the CLI."""
    base = tmp_path_factory.mktemp("lever")
    steps = protocols.to_frame(
        protocols.xu2016_multirate()
        + protocols.xu2016_multiposition()
        + protocols.dynamic_steps(tilted=False)
    )
    lever = get_effect("lever_arm")

    def truth(rng, lot, unit):
        return typical_truth(rng).with_effects((lever, np.array([8, 4, -6, -5, 9, 3, 4, -7, 12.0])))

    mp = pytest.MonkeyPatch()
    mp.setattr(fleet_sim, "OUTLIER_KINDS", BIG_OUTLIERS)
    manifest = simulate_fleet(
        base / "data",
        1,
        10,
        3,
        seed=7,
        sample_rate_hz=RATE_HZ,
        protocol=steps,
        truth_factory=truth,
        outliers=1,
        bad_sessions=1,
    )
    mp.undo()
    code = cli_main(
        ["nightly", str(base / "data"), "--results", str(base / "results"), "--quiet", "--runner", "threads"]
    )
    return base / "data", base / "results", manifest, code


@pytest.mark.slow
def test_nightly_and_rerun_succeed_with_unobservable_lever_arm_components(lever_lot, capsys):
    data, results, manifest, code = lever_lot
    assert code == 1  # the bad session; every unit calibrated
    log = json.loads(sorted((results / "runs").glob("*.json"))[-1].read_text())
    assert log["units_calibrated"] == 10 and log["units_failed"] == [] and "end" in log
    assert len(log["failed_sessions"]) == 1

    def not_json(token):
        pytest.fail(f"{token} in a calibration file is not JSON")

    for path in calibration_files(results):
        doc = json.loads(path.read_text(), parse_constant=not_json)
        load_calibration(path)
        if any(t["name"] == "lever_arm" for t in doc["terms"]):
            lever = next(t for t in doc["terms"] if t["name"] == "lever_arm")
            assert None in lever["stderr"].values()
    unit = manifest["units"][0]["unit"]
    assert cli_main(["rerun", str(data), "--results", str(results), "--unit", unit]) in (0, 1)
    rerun_log = json.loads(
        sorted((results / "runs").glob("*.json"), key=lambda p: p.stat().st_mtime)[-1].read_text()
    )
    assert rerun_log["kind"] == "rerun" and rerun_log["units_calibrated"] == 1


@pytest.mark.slow
def test_every_table_directory_reads_as_one_table_in_pandas_pyarrow_and_duckdb(lever_lot):
    import duckdb

    _, results, _, _ = lever_lot
    store = ResultsStore(results)
    sessions = store.read("sessions")
    assert (sessions["status"] == "failed").sum() == 1
    assert store.read("units")["flagged"].astype(bool).sum() >= 1
    assert store.read("discovery")["effect"].notna().any()
    con = duckdb.connect()
    for name in TABLE_SCHEMAS:
        d = results / "tables" / name
        if not d.is_dir():
            continue
        files = sorted(d.glob("*.parquet"))
        for f in files:
            assert pq.read_schema(f).remove_metadata().equals(TABLE_SCHEMAS[name]), (name, f)
        n = sum(pq.ParquetFile(f).metadata.num_rows for f in files)
        assert len(pd.read_parquet(d)) == n
        assert pads.dataset(d, format="parquet").to_table().num_rows == n
        got = con.execute(f"select count(*) from read_parquet('{d}/*.parquet')").fetchone()[0]
        assert got == n


@pytest.mark.slow
def test_damaged_store_is_refused_repaired_and_the_next_run_completes(lever_lot, tmp_path, capsys):
    data, results0, _, _ = lever_lot
    results = tmp_path / "results"
    shutil.copytree(results0, results)
    os.truncate(results / "tables" / "residuals" / "lot=L01.parquet", 50)
    missing = sorted((results / "calibrations" / "U0002").glob("*.json"))[-1]
    missing.unlink()
    before = calibration_files(results)
    argv = ["nightly", str(data), "--results", str(results), "--quiet", "--runner", "threads"]
    for extra in ([], ["--force"]):
        assert cli_main(argv + extra) == 2
        line = one_line_error(capsys, "nightly")
        assert "tables/residuals/lot=L01.parquet is damaged" in line
        assert f"run 'mimucal repair --results {results}'" in line
        assert calibration_files(results) == before  # a failed run adds no calibration file
    assert cli_main(["repair", "--results", str(results), "--no-reports"]) == 2
    out = capsys.readouterr()
    assert "removed damaged" in out.out and "next 'mimucal nightly' recalibrates" in out.err
    assert ResultsStore(results).verify() == []
    shutil.rmtree(results / "reports")
    assert cli_main(argv) == 1  # the bad session again
    store = ResultsStore(results)
    assert store.verify() == []
    units = store.read("units")
    assert (units["state"] == "calibrated").all() and len(units) == 10
    assert len(store.read("residuals")["unit"].unique()) == 10
    assert (results / "reports" / "L01.html").is_file()  # missing reports rebuilt
    assert (results / "reports" / "index.html").is_file()
    assert cli_main(argv) == 0  # next run: nothing to recalibrate, nothing failed in it
    assert ResultsStore(results).verify() == []


@pytest.mark.slow
def test_an_empty_dataset_exits_3_with_a_warning(tmp_path, capsys, lever_lot):
    (tmp_path / "empty").mkdir()
    code = cli_main(
        [
            "nightly",
            str(tmp_path / "empty"),
            "--results",
            str(tmp_path / "r"),
            "--quiet",
            "--runner",
            "threads",
        ]
    )
    assert code == 3
    assert "warning: no session under" in capsys.readouterr().err


def test_unknown_unit_or_lot_lists_the_ones_that_exist(small_fleet, tmp_path, capsys):
    root, jobs = small_fleet
    store = ResultsStore(tmp_path)
    nightly.store_results(store, calibrate_batch(jobs[:1], False), "run1", "v")
    assert cli_main(["rerun", str(root), "--results", str(tmp_path), "--unit", "U9999"]) == 2
    line = one_line_error(capsys, "rerun")
    assert "'U9999'" in line and "U0001, U0002, U0003" in line
    assert cli_main(["report", "--results", str(tmp_path), "--lot", "L99"]) == 2
    line = one_line_error(capsys, "report")
    assert "'L99'" in line and "L01" in line
    assert cli_main(["calibration", "--results", str(tmp_path), "--unit", "U0002"]) == 2
    line = one_line_error(capsys, "calibration")
    assert "'U0002'" in line and "U0001" in line


@pytest.mark.slow
def test_numpy_runtime_warnings_never_reach_the_terminal_and_become_named_warnings(tmp_path):
    """``mimucal calibrate`` (real processes: pytest's own warning capture would hide them
    in-process), with and without --debug: (1) a unit whose lever-arm components are partly
    unobservable (their repetitions' mean was NumPy's 'Mean of empty slice'): no
    RuntimeWarning, the components named by the protocol note P_LEVER_ARM_UNOBSERVED; (2) a float64 sample
    damaged to 1e160 deg/s (its square overflows in the step's standard deviation): no
    RuntimeWarning, the session warned with W_NUMERIC (and its step W_SATURATED)."""
    import subprocess
    import sys

    steps = protocols.to_frame(
        protocols.xu2016_multirate()
        + protocols.xu2016_multiposition()
        + protocols.dynamic_steps(tilted=False)
    )
    lever = get_effect("lever_arm")
    simulate_fleet(
        tmp_path / "d",
        1,
        1,
        2,
        seed=5,
        sample_rate_hz=RATE_HZ,
        protocol=steps,
        truth_factory=lambda rng, lot, unit: typical_truth(rng).with_effects(
            (lever, np.array([8, 4, -6, -5, 9, 3, 4, -7, 12.0]))
        ),
    )
    simulate_fleet(tmp_path / "o", 1, 1, 3, seed=3, sample_rate_hz=RATE_HZ)
    rep1 = sorted(find_sessions(tmp_path / "o")[0], key=lambda r: r.key.rep)[0]
    table = pq.read_table(rep1.samples_path)
    gx = table.column("gx").to_numpy().astype(np.float64)
    gx[np.flatnonzero(table.column("step").to_numpy() == 20)[-3]] = 1e160
    pq.write_table(
        table.set_column(table.schema.get_field_index("gx"), "gx", pa.array(gx)), rep1.samples_path
    )

    env = {**os.environ, "PYTHONPATH": str(Path(__file__).resolve().parents[1])}
    env.pop("PYTHONWARNINGS", None)

    def calibrate(dataset: str, *extra: str) -> subprocess.CompletedProcess:
        cmd = [sys.executable, "-m", "flows.cli", "calibrate", str(tmp_path / dataset), "--unit", "U0001"]
        done = subprocess.run(cmd + list(extra), capture_output=True, text=True, env=env, timeout=180)
        assert done.returncode == 0, done.stderr
        assert "RuntimeWarning" not in done.stderr and "Warning" not in done.stdout, done.stderr
        return done

    for extra in ((), ("--debug",)):
        text = calibrate("d", *extra).stdout
        # a fact of the protocol, said once, not a repetition's warning
        assert "protocol: P_LEVER_ARM_UNOBSERVED: these dynamic steps do not observe" in text, text
        assert "LEVER_ARM" not in "".join(ln for ln in text.splitlines() if ln.startswith("warning")), text
    text = calibrate("o", "--debug").stdout
    assert "warning rep 1: [W_SATURATED] lot=L01/unit=U0001/rep=1: step 20 " in text
    assert (
        "warning rep 1: [W_NUMERIC] lot=L01/unit=U0001/rep=1: floating-point overflow (1 operation) "
        "while averaging its steps" in text
    ), text
    assert "warning rep 2" not in text and "warning rep 3" not in text


@pytest.mark.slow
def test_disk_full_while_writing_reports_exits_1_and_the_next_run_rebuilds_them(
    lever_lot, tmp_path, capsys, monkeypatch
):
    data, results0, _, _ = lever_lot
    results = tmp_path / "results"
    shutil.copytree(results0, results)
    import reports.lot

    def full(*a, **k):
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(reports.lot, "write_lot_report", full)
    argv = ["nightly", str(data), "--results", str(results), "--quiet", "--runner", "threads"]
    assert cli_main(argv + ["--force"]) == 1
    err = capsys.readouterr().err
    assert "report: lot report L01: OSError: [Errno 28] No space left on device" in err
    store = ResultsStore(results)
    report = results / "reports" / "L01.html"
    assert report.stat().st_mtime_ns < store.partition_path("units", "L01").stat().st_mtime_ns
    monkeypatch.undo()
    assert cli_main(argv) == 0  # nothing to recalibrate; the stale report is rebuilt
    assert report.stat().st_mtime_ns > store.partition_path("units", "L01").stat().st_mtime_ns
