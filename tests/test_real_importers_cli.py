"""Importers (generic column mapping, units, errors) and the `ferraris`, `field`,
`import-raw` commands run end to end on the real recordings."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from flows.cli import main
from schemas.calibration_file import load_calibration
from schemas.errors import E_MISSING_COLUMN, E_NONINCREASING_TIME, E_UNKNOWN_UNIT, SessionError
from schemas.importers import parse_column_mapping, read_section_list, read_table_recording

REAL = Path(__file__).parents[2] / "shared" / "data" / "real"
IMUCAL_CSV = REAL / "imucal" / "example_ferraris_session.csv"
IMUCAL_SECTIONS = REAL / "imucal" / "example_ferraris_session_list.json"
XSENS_ACC, XSENS_GYRO = REAL / "imu_tk" / "xsens_acc.txt", REAL / "imu_tk" / "xsens_gyro.txt"
need_real = pytest.mark.skipif(
    not IMUCAL_CSV.exists() or not XSENS_ACC.exists(), reason=f"real recordings absent under {REAL}"
)

MAPPING = "t=0,gx=4,gy=5,gz=6,ax=1,ay=2,az=3"


def _whitespace_file(path: Path, rng) -> np.ndarray:
    data = np.column_stack([np.arange(50) * 0.01 + 3.0, rng.normal(0, 1, (50, 6))])
    np.savetxt(path, data, fmt="%.9e")
    return data


def test_generic_whitespace_import_with_mapping_and_units(tmp_path):
    rng = np.random.default_rng(3)
    data = _whitespace_file(tmp_path / "imu.txt", rng)
    rec = read_table_recording(
        tmp_path / "imu.txt",
        parse_column_mapping(MAPPING),
        gyro_unit="rad/s",
        accel_unit="m/s^2",
        g_local=9.8,
    )
    np.testing.assert_allclose(rec.t, data[:, 0] - 3.0, atol=1e-12)
    np.testing.assert_allclose(rec.gyro, data[:, 4:7] * 180 / math.pi)
    np.testing.assert_allclose(rec.accel, data[:, 1:4] / 9.8)
    assert (rec.gyro_unit, rec.accel_unit) == ("deg/s", "g")
    assert rec.rate_hz == pytest.approx(100.0)
    mg = read_table_recording(tmp_path / "imu.txt", parse_column_mapping(MAPPING), "LSB", "mg")
    np.testing.assert_allclose(mg.accel, data[:, 1:4] / 1000)
    assert mg.gyro_unit == "LSB"


def test_csv_without_time_column_uses_the_rate(tmp_path):
    df = pd.DataFrame(np.arange(24.0).reshape(4, 6), columns=["a", "b", "c", "d", "e", "f"])
    df.to_csv(tmp_path / "x.csv", index=False)
    cols = parse_column_mapping("gx=a,gy=b,gz=c,ax=d,ay=e,az=f")
    rec = read_table_recording(tmp_path / "x.csv", cols, "deg/s", "g", rate_hz=50.0)
    np.testing.assert_allclose(rec.t, [0, 0.02, 0.04, 0.06])
    with pytest.raises(SessionError) as err:
        read_table_recording(tmp_path / "x.csv", cols, "deg/s", "g")
    assert err.value.code == E_MISSING_COLUMN and "--rate" in str(err.value)


def test_import_errors_name_file_column_and_code(tmp_path):
    rng = np.random.default_rng(4)
    data = _whitespace_file(tmp_path / "imu.txt", rng)
    with pytest.raises(SessionError) as err:
        read_table_recording(
            tmp_path / "imu.txt", parse_column_mapping(MAPPING.replace("az=3", "az=9")), "LSB", "LSB"
        )
    assert err.value.code == E_MISSING_COLUMN and err.value.column == "9"
    assert "imu.txt" in str(err.value)
    with pytest.raises(SessionError) as err:
        read_table_recording(tmp_path / "imu.txt", parse_column_mapping(MAPPING), "furlong/s", "LSB")
    assert err.value.code == E_UNKNOWN_UNIT
    data[10, 0] = data[9, 0]
    np.savetxt(tmp_path / "bad.txt", data)
    with pytest.raises(SessionError) as err:
        read_table_recording(tmp_path / "bad.txt", parse_column_mapping(MAPPING), "LSB", "LSB")
    assert err.value.code == E_NONINCREASING_TIME and "row 10" in str(err.value)
    with pytest.raises(ValueError, match="not one of"):
        parse_column_mapping("gq=1")


def test_section_list_json_and_csv_agree(tmp_path):
    sec = {"x_p": (1, 5), "x_rot": (7, 9)}
    (tmp_path / "s.json").write_text(json.dumps({k: {"start": a, "end": b} for k, (a, b) in sec.items()}))
    pd.DataFrame({k: {"start": a, "end": b} for k, (a, b) in sec.items()}).T.to_csv(tmp_path / "s.csv")
    assert read_section_list(tmp_path / "s.json") == sec == read_section_list(tmp_path / "s.csv")


@need_real
def test_cli_ferraris_on_the_imucal_session(tmp_path, capsys):
    out = tmp_path / "ferraris.json"
    rc = main(
        [
            "ferraris",
            str(IMUCAL_CSV),
            "--sections",
            str(IMUCAL_SECTIONS),
            "--rate",
            "102.4",
            "--out",
            str(out),
        ]
    )
    assert rc == 0
    cal = load_calibration(out)
    assert cal.kind == "ferraris" and (cal.gyro_unit, cal.accel_unit) == ("deg/s", "g")
    doc = json.loads(out.read_text())
    assert doc["fit"]["static_norm_err_max_mg"] < 1.0
    assert [t["name"] for t in doc["terms"]] == ["gyro_g_sensitivity"]
    assert doc["terms"][0]["units"]["Gxx"] == "deg/s per g"
    # without --rate the rotations cannot be integrated: a user error, exit code 2
    assert main(["ferraris", str(IMUCAL_CSV), "--sections", str(IMUCAL_SECTIONS), "--out", str(out)]) == 2
    assert "--rate" in capsys.readouterr().err


@pytest.mark.slow
@need_real
def test_cli_field_on_the_xsens_recording(tmp_path):
    out, poses = tmp_path / "field.json", tmp_path / "poses.csv"
    rc = main(
        [
            "field",
            str(XSENS_ACC),
            str(XSENS_GYRO),
            "--acc-bias",
            "32768",
            "--gyro-scale",
            "1/6258",
            "--init-static",
            "50",
            "--g-local",
            "9.81744",
            "--gyro-g-sensitivity",
            "--no-held-out",
            "--out",
            str(out),
            "--poses",
            str(poses),
        ]
    )
    assert rc == 0
    cal = load_calibration(out)
    assert cal.kind == "field" and (cal.gyro_unit, cal.accel_unit) == ("LSB", "LSB")
    assert [t.name for t in cal.terms] == ["gyro_g_sensitivity"]
    pm = pd.read_csv(poses)
    w, f = cal.apply(pm[["gx", "gy", "gz"]].to_numpy(), pm[["ax", "ay", "az"]].to_numpy())
    assert np.abs(np.linalg.norm(f, axis=1) - 1).max() < 0.5e-3  # g
    # deg/s at rest: without the g-sensitivity term up to 0.23 deg/s, with it 0.016 RMS
    assert np.sqrt(np.mean(w**2)) < 0.03 and np.abs(w).max() < 0.1


@need_real
def test_cli_import_raw_writes_layout_and_pose_means(tmp_path):
    out, poses = tmp_path / "rec.parquet", tmp_path / "poses.csv"
    rc = main(
        [
            "import-raw",
            str(IMUCAL_CSV),
            "--columns",
            "gx=gyr_x,gy=gyr_y,gz=gyr_z,ax=acc_x,ay=acc_y,az=acc_z",
            "--gyro-unit",
            "deg/s",
            "--accel-unit",
            "m/s^2",
            "--g-local",
            "9.81",
            "--rate",
            "102.4",
            "--out",
            str(out),
            "--poses",
            str(poses),
        ]
    )
    assert rc == 0
    df = pd.read_parquet(out)
    assert list(df.columns) == ["t", "gx", "gy", "gz", "ax", "ay", "az"] and len(df) == 10376
    side = json.loads(out.with_suffix(".parquet.json").read_text())
    assert (side["gyro_unit"], side["accel_unit"], side["g_local"]) == ("deg/s", "g", 9.81)
    pm = pd.read_csv(poses)
    # the six annotated static poses are each found inside one detected pose
    sec = read_section_list(IMUCAL_SECTIONS)
    for name in ("x_p", "x_a", "y_p", "y_a", "z_p", "z_a"):
        a, b = sec[name]
        mid = (a + b) // 2
        assert ((pm["start"] <= mid) & (pm["end"] > mid)).sum() == 1, name
