"""Text logs as loggers write them: key,value preamble lines, comment lines, header
detection, full-scale ranges, and errors that name the line; `mimucal field` on the
MPU-6050 log as it is."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from flows.cli import main
from schemas.calibration_file import load_calibration
from schemas.errors import E_UNREADABLE_FILE, SessionError
from schemas.importers import parse_range, read_table_recording, sniff_table

REAL = Path(__file__).parents[2] / "shared" / "data" / "real"
MPU = REAL / "mpu6050_tedaldi" / "example_data_calibration.csv"
need_mpu = pytest.mark.skipif(not MPU.exists(), reason=f"real recordings absent under {REAL}")


def _log(
    path: Path,
    rows: np.ndarray,
    preamble=("Fs,50", "Logging Type,0", "Initialization time,2.5"),
    header="ax,ay,az,gx,gy,gz",
    comments=True,
) -> None:
    lines = list(preamble)
    if comments:
        lines.append("# logger v1.2, units: counts")
    lines.append(header)
    for i, r in enumerate(rows):
        if comments and i == 3:
            lines.append("// a comment in the middle")
            lines.append("")
        lines.append(",".join(str(int(v)) for v in r))
    path.write_text("\n".join(lines) + "\n")


def test_preamble_comments_and_header_are_recognised(tmp_path):
    rng = np.random.default_rng(11)
    rows = rng.integers(-2000, 2000, (40, 6))
    _log(tmp_path / "log.csv", rows)
    layout = sniff_table(tmp_path / "log.csv")
    assert layout.preamble == {"Fs": "50", "Logging Type": "0", "Initialization time": "2.5"}
    assert layout.columns == ["ax", "ay", "az", "gx", "gy", "gz"] and layout.header_line == 5
    rec = read_table_recording(tmp_path / "log.csv", None, "LSB", "LSB")
    assert len(rec) == 40 and rec.rate_hz == 50.0
    np.testing.assert_allclose(rec.t, np.arange(40) / 50.0)
    np.testing.assert_array_equal(rec.accel, rows[:, :3])
    np.testing.assert_array_equal(rec.gyro, rows[:, 3:])
    assert rec.metadata["preamble"]["Initialization time"] == "2.5"


def test_headerless_semicolon_log_with_mapping(tmp_path):
    rows = np.arange(60.0).reshape(10, 6)
    (tmp_path / "x.txt").write_text("\n".join(";".join(f"{v:g}" for v in r) for r in rows) + "\n")
    rec = read_table_recording(
        tmp_path / "x.txt",
        {"gx": "0", "gy": "1", "gz": "2", "ax": "3", "ay": "4", "az": "5"},
        "LSB",
        "LSB",
        rate_hz=10,
    )
    np.testing.assert_array_equal(rec.gyro, rows[:, :3])


@pytest.mark.parametrize(
    "bad_line, expect",
    [
        ("1,2,3", "line 9: 3 fields, expected 6"),
        ("1,2,3,x,5,6", "line 9: 'x' is not a number"),
    ],
)
def test_a_bad_line_is_named(tmp_path, bad_line, expect):
    rows = np.ones((10, 6))
    _log(tmp_path / "log.csv", rows, comments=False)
    lines = (tmp_path / "log.csv").read_text().splitlines()
    lines[8] = bad_line  # 1-based line 9: the fourth data row
    (tmp_path / "log.csv").write_text("\n".join(lines) + "\n")
    with pytest.raises(SessionError) as err:
        read_table_recording(tmp_path / "log.csv", None, "LSB", "LSB")
    assert err.value.code == E_UNREADABLE_FILE and expect in str(err.value)
    assert "log.csv" in str(err.value) and "\n" not in str(err.value)


def test_file_without_numbers_is_named(tmp_path):
    (tmp_path / "notes.csv").write_text("# only\nsome,words\nand,more\n")
    with pytest.raises(SessionError, match="no two consecutive lines of numbers"):
        read_table_recording(tmp_path / "notes.csv", None, "LSB", "LSB")


def test_ranges():
    assert parse_range("2g", "accel") == 2.0 and parse_range("16G", "accel") == 16.0
    assert parse_range("250dps", "gyro") == 250.0 and parse_range("2000 deg/s", "gyro") == 2000.0
    for text, kind in (("250dps", "accel"), ("2g", "gyro"), ("-2g", "accel"), ("fast", "gyro")):
        with pytest.raises(ValueError, match="range"):
            parse_range(text, kind)


@need_mpu
def test_cli_field_reads_the_mpu6050_log_as_it_is(tmp_path, capsys):
    """The documented command (docs/real-data.md) without the held-out refits."""
    out = tmp_path / "mpu.json"
    rc = main(
        [
            "field",
            str(MPU),
            "--accel-range",
            "2g",
            "--gyro-range",
            "250dps",
            "--no-held-out",
            "--out",
            str(out),
        ]
    )
    assert rc == 0
    printed = capsys.readouterr().out
    assert "static poses used" in printed and "rejected" in printed and "moves used" in printed
    cal = load_calibration(out)
    assert cal.kind == "field" and (cal.gyro_unit, cal.accel_unit) == ("LSB", "LSB")
    # the starting scales came from the ranges: 16384 counts per g, 131.07 counts per deg/s,
    # and the fit stays within the datasheet's +/-3 % sensitivity tolerance of them
    np.testing.assert_allclose(np.diag(cal.K_a) * 16384, 1, atol=0.03)
    np.testing.assert_allclose(np.diag(cal.K_g) * 32768 / 250, 1, atol=0.03)
    doc = json.loads(out.read_text())
    assert doc["poses"]["detector"]["floor_from"] == "initial"  # from 'Initialization time,36.5'
    assert doc["poses"]["used"][0]["end_s"] > 30  # the 36.5 s initial rest is the first pose
    # the MPU-6050's int16 gyro saturates in three fast moves: those are listed, not fitted
    assert len(doc["poses"]["moves_unusable"]) >= 1
    assert doc["fit"]["figures"]["after_norm_rms_mg"] < doc["fit"]["figures"]["before_norm_rms_mg"]
    # a range on a physical unit is a user error with one line
    assert (
        main(
            ["field", str(MPU), "--accel-unit", "g", "--accel-range", "2g", "--out", str(tmp_path / "x.json")]
        )
        == 2
    )
    assert "--accel-range applies to raw counts" in capsys.readouterr().err
