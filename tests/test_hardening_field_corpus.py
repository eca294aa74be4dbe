"""Field units and the results store under hostile input (issue 35): one test per case.

The whole-night cases share one ``mimucal nightly`` over a lot of 21 copies of the real
MPU-6050 recording, each unit but H0 made hostile in one way (``hostile_field_night``,
tests/conftest.py); the rest run without Prefect. Each expects a named failure of the hostile
unit (its code, one line), the good unit calibrated, the night's tables, reports and run log
written, and nothing of a file outside the dataset anywhere under the results folder."""

from __future__ import annotations

import json
import os
import shutil
import signal
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from flows import runtime

from conftest import (
    FIELD_LOT_OPTIONS,
    PASSWD_MARKERS,
    REAL_FIELD_LOG,
    make_hostile_field_lot,
)

runtime.ensure_environment()

from flows.cli import main as cli_main  # noqa: E402
from flows.field_units import calibrate_field_unit_job, calibrate_recording  # noqa: E402
from schemas.contract import parse_metadata  # noqa: E402
from schemas.errors import SessionError  # noqa: E402
from schemas.field_dataset import (  # noqa: E402
    FIELD_OPTIONS,
    OptionError,
    check_options,
    find_field_recordings,
    loads_bounded,
)
from schemas.limits import LimitsError, config_from_toml  # noqa: E402
from schemas.results_store import ResultsStore  # noqa: E402
from schemas.unit_plan import plan_field_units  # noqa: E402

pytestmark = pytest.mark.skipif(not REAL_FIELD_LOG.is_file(), reason="the real MPU-6050 recording is absent")


def _sessions(night) -> pd.DataFrame:
    return ResultsStore(night["results"]).read("sessions").set_index("unit")


def _assert_failed(night, unit: str, code: str, *words: str) -> str:
    """The unit's only session failed with ``code``, one line naming the unit and ``words``;
    the unit has no calibration; the good unit H0 is calibrated."""
    s = _sessions(night)
    row = s.loc[unit]
    msg = row["message"]
    assert row["status"] == "failed" and row["error_code"] == code, (unit, msg)
    assert "\n" not in msg and f"unit={unit}" in msg, msg
    for w in words:
        assert w in msg, (w, msg)
    units = ResultsStore(night["results"]).read("units").set_index("unit")
    assert units.loc[unit, "state"] == "failed"
    assert units.loc["H0", "state"] == "calibrated"
    return msg


# --- the whole night ----------------------------------------------------------------------------
def test_the_night_completes_with_every_hostile_unit_failed_by_name(hostile_field_night):
    night = hostile_field_night
    assert night["rc"] == 1  # some units failed; not 5 (the run failed unexpectedly)
    results = night["results"]
    s = _sessions(night)
    assert set(s.index) == set(night["corpus"])
    for unit, (what, code) in night["corpus"].items():
        if code is None:
            assert s.loc[unit, "status"] in ("ok", "warned"), (unit, what, s.loc[unit, "message"])
        else:
            assert s.loc[unit, "error_code"] == code, (unit, what, s.loc[unit, "message"])
    # the night's tables, reports and run log are written
    store = ResultsStore(results)
    assert len(store.read("parameters")) and len(store.read("summary"))
    assert (results / "reports" / "F1.html").is_file()
    (log_path,) = (results / "runs").glob("*.json")
    log = json.loads(log_path.read_text())
    assert log["outcome"] == "failures" and log.get("end")
    assert ": some units failed; " in log["summary"], log["summary"]
    assert len(log["failed_sessions"]) == sum(code is not None for _, code in night["corpus"].values())
    assert store.verify() == []


def test_no_content_of_a_file_outside_the_dataset_is_under_the_results(hostile_field_night):
    outside_text = Path("/etc/passwd").read_bytes()
    markers = [m for m in PASSWD_MARKERS if m in outside_text]
    assert markers, "the test needs /etc/passwd to hold a marker"
    for p in hostile_field_night["results"].rglob("*"):
        if p.is_file():
            data = p.read_bytes()
            assert not any(m in data for m in markers), p
    assert not any(m.decode() in hostile_field_night["stderr"] for m in markers)


# --- one test per case (the night above) --------------------------------------------------------
def test_a_date_out_of_range_fails_its_unit(hostile_field_night):
    _assert_failed(hostile_field_night, "H1", "E_BAD_METADATA", "session_start", "1970-2199")


def test_deeply_nested_json_fails_its_unit(hostile_field_night):
    _assert_failed(hostile_field_night, "H2", "E_BAD_OPTION", "nested more than 16 levels deep")
    _assert_failed(hostile_field_night, "H3", "E_BAD_OPTION", "larger than 65536 bytes")


def test_a_recording_linked_to_etc_passwd_is_refused_unread(hostile_field_night):
    _assert_failed(hostile_field_night, "H4", "E_BAD_PATH", "symbolic link", "--follow-symlinks")


def test_an_options_file_linked_out_of_the_dataset_is_refused(hostile_field_night):
    _assert_failed(hostile_field_night, "H5", "E_BAD_PATH", "field.json is a symbolic link")


def test_a_valid_log_linked_from_outside_is_not_calibrated(hostile_field_night):
    _assert_failed(hostile_field_night, "H6", "E_BAD_PATH", "symbolic link")


def test_a_negative_g_local_is_refused(hostile_field_night):
    _assert_failed(hostile_field_night, "H7", "E_BAD_OPTION", "'g_local' = -9.8 is outside [9.7, 9.9]")


def test_a_zero_accel_scale_is_refused(hostile_field_night):
    _assert_failed(hostile_field_night, "H8", "E_BAD_OPTION", "'acc_scale' = 0 is outside (0,")


def test_three_axes_on_one_column_are_refused(hostile_field_night):
    _assert_failed(hostile_field_night, "H9", "E_BAD_OPTION", "maps ax, ay, az to the same column")


def test_an_implausible_fit_is_never_stored_as_calibrated(hostile_field_night):
    msg = _assert_failed(hostile_field_night, "H10", "E_IMPLAUSIBLE", "not those of a working sensor")
    assert "angle_rms_deg" in msg or "w0_" in msg
    assert not (hostile_field_night["results"] / "calibrations" / "H10").exists()


def test_a_fifo_recording_is_refused_without_opening_it(hostile_field_night):
    _assert_failed(hostile_field_night, "H11", "E_BAD_PATH", "is a FIFO, not a regular file")


def test_a_dev_zero_link_is_refused(hostile_field_night):
    _assert_failed(hostile_field_night, "H12", "E_BAD_PATH", "symbolic link (to /dev/zero)")


def test_binary_garbage_fails_its_unit(hostile_field_night):
    _assert_failed(hostile_field_night, "H13", "E_UNREADABLE_FILE", "cannot read as text")


def test_a_header_only_log_fails_its_unit(hostile_field_night):
    _assert_failed(hostile_field_night, "H14", "E_UNREADABLE_FILE", "no two consecutive lines of numbers")


def test_a_crlf_log_is_calibrated_as_the_original(hostile_field_night):
    params = ResultsStore(hostile_field_night["results"]).read("parameters")
    a = params[params.unit == "H0"].set_index(["model", "parameter"])["value"]
    b = params[params.unit == "H15"].set_index(["model", "parameter"])["value"]
    np.testing.assert_allclose(b.loc[a.index].to_numpy(), a.to_numpy(), rtol=1e-9, atol=1e-12)


def test_a_utf16_log_fails_its_unit(hostile_field_night):
    _assert_failed(hostile_field_night, "H16", "E_UNREADABLE_FILE", "cannot read as text")


def test_constant_data_fails_its_unit(hostile_field_night):
    _assert_failed(hostile_field_night, "H17", "E_FIELD_TOO_FEW_POSES", "static poses")


def test_values_beyond_full_scale_fail_their_unit(hostile_field_night):
    _assert_failed(hostile_field_night, "H18", "E_FIELD_TOO_FEW_POSES")


def test_a_json_nan_option_is_refused(hostile_field_night):
    _assert_failed(hostile_field_night, "H19", "E_BAD_OPTION", "'window' = nan is not a finite number")


def test_a_log_beyond_the_size_limit_is_refused_unread(hostile_field_night):
    _assert_failed(hostile_field_night, "H20", "E_UNREADABLE_FILE", "257 MiB, more than", "not read")


# --- without Prefect ----------------------------------------------------------------------------
HOSTILE_VALUES = [
    float("nan"),
    float("inf"),
    -float("inf"),
    1e308,
    -1e308,
    0,
    -1,
    2**70,
    "",
    "x" * 10_000,
    "1e999",
    "1/0",
    "nan",
    [1, [2]],
    {"a": 1},
    True,
]


def test_every_option_given_hostile_values_is_refused_or_used_never_raised(tmp_path):
    """Each option of field.json with each hostile value: refused at the boundary with a
    one-line OptionError naming the option, or accepted and then the recording fails by name
    or is calibrated; nothing raises out of the unit's calibration."""
    accepted = []
    for name in FIELD_OPTIONS:
        for v in HOSTILE_VALUES:
            try:
                doc = check_options(json.loads(json.dumps({name: v})), "options file f.json")
            except OptionError as exc:
                assert name in str(exc) and "f.json" in str(exc) and "\n" not in str(exc), (name, v, exc)
                assert exc.code in ("E_BAD_OPTION", "E_BAD_METADATA")
                assert len(str(exc)) < 400, (name, v)
                continue
            accepted.append((name, doc[name]))
    # what passes is in range: fit the real recording with each (a few, all distinct)
    d = tmp_path / "lot=F1" / "unit=U1" / "field"
    d.mkdir(parents=True)
    (tmp_path / "lot=F1" / "field.json").write_text(json.dumps(FIELD_LOT_OPTIONS))
    shutil.copy(REAL_FIELD_LOG, d / "log.csv")
    assert {n for n, _ in accepted} <= {"columns", "init_static", "acc_bias", "misalignment_prior"}, accepted
    for name, value in accepted:
        (d / "field.json").write_text(json.dumps({name: value}))
        (ref,), _ = find_field_recordings(tmp_path)
        out, _ = calibrate_recording(ref)
        assert out.status in ("ok", "warned") or (out.code and "\n" not in out.message), (name, value)


def test_the_bounded_json_loader_counts_depth_outside_strings():
    assert loads_bounded('{"a": "[[[[[[[[[[[[[[[[[[[[[[[[[[[[["}') == {"a": "[" * 29}
    assert loads_bounded("[" * 16 + "]" * 16) is not None
    with pytest.raises(ValueError, match="nested more than 16"):
        loads_bounded("[" * 17 + "]" * 17)


def test_links_inside_the_dataset_are_followed_only_with_follow_symlinks(tmp_path):
    make_hostile_field_lot(tmp_path / "d", tmp_path, units=["H0", "H6"])
    h1 = tmp_path / "d" / "lot=F1" / "unit=H1" / "field"
    h1.mkdir(parents=True)
    (h1 / "log.csv").symlink_to(tmp_path / "d" / "lot=F1" / "unit=H0" / "field" / "log.csv")
    refs, _ = find_field_recordings(tmp_path / "d")
    by_unit = {r.key.unit: r for r in refs}
    assert by_unit["H1"].error.code == "E_BAD_PATH" and by_unit["H6"].error.code == "E_BAD_PATH"
    refs, _ = find_field_recordings(tmp_path / "d", follow_symlinks=True)
    by_unit = {r.key.unit: r for r in refs}
    assert by_unit["H1"].error is None  # inside the dataset: followed
    assert "outside the dataset root" in str(by_unit["H6"].error)  # outside: never


def test_a_bug_on_one_recording_fails_that_recording_not_the_unit_job(tmp_path, monkeypatch):
    make_hostile_field_lot(tmp_path / "d", tmp_path, units=["H0"])
    (job,), _, _ = plan_field_units(tmp_path / "d", {})

    def bug(ref):
        raise ZeroDivisionError("injected")

    monkeypatch.setattr("flows.field_units.calibrate_recording", bug)
    res = calibrate_field_unit_job(job, run_discovery=False)
    (s,) = res.outcome.sessions
    assert s.code == "E_INTERNAL" and "ZeroDivisionError: injected" in s.message and not res.calibrated


def test_turntable_session_start_is_range_checked_too():
    md = {
        "gyro_unit": "deg/s",
        "accel_unit": "g",
        "gyro_range_dps": "300",
        "accel_range_g": "8",
        "session_start": "9999-12-31T23:59:59Z",
    }
    with pytest.raises(SessionError) as exc:
        parse_metadata(md, "lot=L/unit=U/rep=1")
    assert exc.value.code == "E_BAD_METADATA" and "1970-2199" in str(exc.value)
    md["session_start"] = "2026-11-20T02:00:00Z"
    assert parse_metadata(md, "lot=L/unit=U/rep=1").session_start == "2026-11-20T02:00:00Z"


def test_a_fifo_in_a_turntable_session_is_fingerprinted_without_opening_it(tmp_path):
    from schemas.dataset import fingerprint, read_session_files

    os.mkfifo(tmp_path / "samples.parquet")
    (tmp_path / "steps.parquet").write_bytes(b"x")
    signal.alarm(10)  # a blocking open() would hang the suite
    try:
        assert fingerprint(tmp_path).startswith("xxh3:")
        files = read_session_files(tmp_path)  # the session's one read never opens it either
        assert files.samples is None and files.fingerprint == fingerprint(tmp_path)
    finally:
        signal.alarm(0)


@pytest.mark.parametrize(
    "toml, words",
    [
        ("[limits]\nk_g11 = {min = nan}", "min: nan is not a finite number"),
        ("[limits]\nk_g11 = {max = inf}", "max: inf is not a finite number"),
        ('[limits]\nf0_x = {max = "1e999 mg"}', "'1e999 mg' is not a finite number"),
        ("[outliers]\nz_threshold = nan", "z_threshold = nan is not a finite number"),
        ('[outliers]\nrobust_models = ["gyr"]', "unknown model(s) ['gyr']"),
    ],
)
def test_non_finite_or_unknown_qa_settings_are_refused_naming_the_file(toml, words):
    with pytest.raises(LimitsError) as exc:
        config_from_toml(toml, source="qa.toml")
    assert str(exc.value).startswith("qa.toml: ") and words in str(exc.value) and "\n" not in str(exc.value)


def test_mimucal_field_refuses_bad_options_and_implausible_fits(tmp_path, capsys):
    out = tmp_path / "cal.json"
    base = ["field", str(REAL_FIELD_LOG), "--accel-range", "2g", "--gyro-range", "250dps", "--out", str(out)]
    assert cli_main([*base, "--g-local", "-9.8"]) == 2
    assert "--g-local = -9.8 is outside" in capsys.readouterr().err
    assert cli_main([*base, "--no-held-out", "--gyro-scale", "1000"]) == 2
    err = capsys.readouterr().err
    assert "[E_IMPLAUSIBLE]" in err and "no calibration written" in err and not out.exists()


# --- the store and the commands that write --------------------------------------------------------
@pytest.fixture
def store_copy(hostile_field_night, tmp_path) -> Path:
    """A copy of the hostile night's results store (H0 and H15 calibrated)."""
    dst = tmp_path / "results"
    shutil.copytree(hostile_field_night["results"], dst, symlinks=True)
    return dst


def test_a_garbage_calibration_file_is_found_moved_and_the_previous_one_restored(store_copy, capsys):
    store = ResultsStore(store_copy)
    ((ts, current),) = store.calibration_files("H0")
    older = current.with_name("20200101T000000.000000Z.json")
    shutil.copy(current, older)  # a previous good calibration of the unit
    current.write_bytes(np.random.default_rng(35).bytes(3000))
    problems = store.verify()
    assert any("H0" in p and "not a mimucal calibration file" in p for p in problems)
    assert cli_main(["calibration", "--results", str(store_copy), "--unit", "H0"]) == 2
    assert "not a JSON text" in capsys.readouterr().err  # one line, no UnicodeDecodeError
    assert cli_main(["repair", "--results", str(store_copy), "--no-reports"]) == 0
    assert list((store_copy / "damaged" / "calibrations" / "H0").iterdir())
    units = store.read("units").set_index("unit")
    assert units.loc["H0", "calibration_file"] == str(older.relative_to(store_copy))
    assert units.loc["H0", "state"] == "stale" and store.verify() == []
    assert cli_main(["calibration", "--results", str(store_copy), "--unit", "H0"]) in (0, 4)


def test_store_json_qa_config_and_a_directory_for_a_table_are_checked_and_repaired(store_copy):
    store = ResultsStore(store_copy)
    store.format_path.write_bytes(b"\xff\xfe garbage")
    store.qa_config_path.write_text("[limits]\nk_g11 = {min = nan}\n")
    (table,) = store.partitions("residuals").values() or store.partitions("parameters").values()
    table.unlink()
    table.mkdir()
    problems = "\n".join(store.verify())
    assert "store.json is not JSON" in problems and "qa-config.toml" in problems
    assert f"{table} is damaged" in problems
    assert cli_main(["repair", "--results", str(store_copy), "--no-reports"]) == 2  # tables need the data
    assert json.loads(store.format_path.read_text())["format_version"] == "2.0"
    assert not store.qa_config_path.exists() and not table.exists()
    assert store.verify() == []


def test_with_follow_symlinks_links_out_of_the_dataset_are_still_refused_and_the_rerun_says_so(
    hostile_field_night, store_copy, capsys
):
    """--follow-symlinks follows links inside the dataset only: the unit whose log leads to
    /etc/passwd fails again, by name (a valid log elsewhere, H6, likewise: see
    test_links_inside_the_dataset_are_followed_only_with_follow_symlinks); the rerun's exit
    code (1), run log and summary say "some units failed" (not "the run failed"), and
    nothing of /etc/passwd reaches the results."""
    argv = ["rerun", str(hostile_field_night["data"]), "--results", str(store_copy), "--unit", "H4"]
    assert cli_main([*argv, "--follow-symlinks", "--no-discovery"]) == 1
    out = capsys.readouterr()
    assert "outside the dataset root" in out.err
    assert ": some units failed; " in out.out, out.out
    s = ResultsStore(store_copy).read("sessions").set_index("unit")
    assert s.loc["H4", "error_code"] == "E_BAD_PATH" and "outside the dataset root" in s.loc["H4", "message"]
    logs = [json.loads(p.read_text()) for p in (store_copy / "runs").glob("*.json")]
    (rerun,) = [g for g in logs if g["kind"] == "rerun"]
    assert rerun["outcome"] == "failures" and rerun.get("end")
    assert ": some units failed; " in rerun["summary"]
    markers = [m for m in PASSWD_MARKERS if m in Path("/etc/passwd").read_bytes()]
    for p in store_copy.rglob("*"):
        if p.is_file():
            assert not any(m in p.read_bytes() for m in markers), p


def test_apply_refuses_to_write_over_its_raw_input(store_copy, tmp_path, capsys):
    cal = ResultsStore(store_copy).calibration_files("H0")[0][1]
    raw = tmp_path / "raw.csv"
    raw.write_text("gx,gy,gz,ax,ay,az\n1,2,3,4,5,6\n")
    link = tmp_path / "link.csv"
    link.symlink_to(raw)
    before = raw.read_bytes()
    for out in (raw, link):
        argv = ["apply", str(cal), str(raw), str(out), "--gyro-unit", "LSB", "--accel-unit", "LSB"]
        assert cli_main(argv) == 2
        assert "OUT is the raw input RAW" in capsys.readouterr().err
    assert raw.read_bytes() == before


def test_report_pdf_refuses_a_path_inside_the_results_store(store_copy, capsys):
    victims = [
        store_copy / ".lock",
        store_copy / "store.json",
        ResultsStore(store_copy).calibration_files("H0")[0][1],
    ]
    for v in victims:
        before = v.read_bytes() if v.exists() else None
        assert cli_main(["report", "--results", str(store_copy), "--lot", "F1", "--pdf", str(v)]) == 2
        assert "inside the results store" in capsys.readouterr().err
        assert (v.read_bytes() if v.exists() else None) == before


def test_a_run_that_fails_unexpectedly_exits_5_and_its_log_says_so(tmp_path, monkeypatch, capsys):
    make_hostile_field_lot(tmp_path / "d", tmp_path, units=["H0"])
    from flows import nightly

    def down(*a, **k):
        raise RuntimeError("injected after the run log was written")

    monkeypatch.setattr(nightly, "reflag_after_update", down)
    r = tmp_path / "r"
    argv = ["nightly", str(tmp_path / "d"), "--results", str(r), "--runner", "threads", "--quiet"]
    assert cli_main(argv) == 5
    assert "the run failed: RuntimeError: injected" in capsys.readouterr().err
    (log_path,) = (r / "runs").glob("*.json")
    log = json.loads(log_path.read_text())
    assert log["outcome"] == "run failed" and "injected" in log["error"] and "end" not in log
    assert ": the run failed; " in log["summary"], log["summary"]
