"""`mimucal noise` on the real MPU-6050 static recording (Tedaldi et al., 449 s at 100 Hz, raw
counts, +/-250 deg/s and +/-2 g) and on bad input; the synthesis round trip from its fitted
model. One analysis of the real recording is shared by the module (~1 s)."""

from __future__ import annotations

import contextlib
import io
import json
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from calib_core.noise import NoiseModel, synthesize
from calib_core.noise.allan import allan_curve
from flows.cli import main as cli_main

STATIC = (
    Path(__file__).resolve().parents[1].parent
    / "shared/data/real/mpu6050_tedaldi/example_data_tinit_calc.csv"
)
if not STATIC.is_file():
    STATIC = Path("/work/shared/data/real/mpu6050_tedaldi/example_data_tinit_calc.csv")
RAW = ["--gyro-unit", "counts", "--accel-unit", "counts", "--gyro-range", "250dps", "--accel-range", "2g"]


def run_cli(*argv) -> tuple[int, str, str]:
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        code = cli_main(["noise", *map(str, argv)])
    return code, out.getvalue(), err.getvalue()


@pytest.fixture(scope="module")
def mpu(tmp_path_factory):
    if not STATIC.is_file():
        pytest.skip(f"the real MPU-6050 static recording is not at {STATIC}")
    d = tmp_path_factory.mktemp("noise")
    code, out, err = run_cli(STATIC, *RAW, "--json", d / "noise.json", "--kalibr-yaml", d / "imu.yaml")
    assert code == 0, err
    return json.loads((d / "noise.json").read_text()), (d / "imu.yaml").read_text(), out


def test_real_recording_names_the_38_hz_gyro_y_line(mpu):
    doc, _, out = mpu
    (line,) = [ln for ln in doc["channels"]["gy"]["periodic"] if abs(ln["frequency_hz"] - 38.0) < 0.1]
    assert 37.9 < line["frequency_hz"] < 38.1
    assert 0.012 < line["amplitude"] < 0.022 and line["unit"] == "deg/s"
    assert line["psd_ratio_to_median"] > 5
    for ch in ("gx", "ax", "ay", "az"):  # no line near 38 Hz anywhere else
        assert all(abs(ln["frequency_hz"] - 38.0) > 0.5 for ln in doc["channels"][ch]["periodic"])
    assert "line 37.99 Hz" in out


def test_real_recording_every_coefficient_has_unit_and_interval(mpu):
    doc, _, _ = mpu
    assert doc["rate_hz"] == 100.0 and 449 < doc["duration_s"] < 450
    expected_units = {
        "g": ("deg", "deg/sqrt(h)", "deg/h", "deg/h/sqrt(h)", "deg/h^2"),
        "a": ("m/s", "m/s/sqrt(h)", "mg", "m/s/h/sqrt(h)", "m/s/h^2"),
    }
    names = ("quantization", "white", "bias_instability", "random_walk", "ramp")
    for name, ch in doc["channels"].items():
        for process, unit in zip(names, expected_units[name[0]]):
            entry = ch["coefficients"][process]
            assert entry["unit"] == unit
            assert entry["lo"] is not None and entry["hi"] is not None and entry["hi"] >= entry["lo"]
            if entry["value"] is None:
                assert entry["reason"].startswith("not named")
            else:
                assert entry["lo"] <= entry["value"] <= entry["hi"]
        assert ch["coefficients"]["white"]["value"] is not None
        allan = ch["allan"]
        assert len(allan["tau_s"]) == len(allan["adev"]) == len(allan["adev_lo"]) >= 10
        assert ch["fit"]["fraction_within_ci"] >= 0.9, (name, ch["fit"])


def test_real_recording_white_noise_against_an_independent_estimate(mpu):
    """White noise from the successive differences of the raw samples (sigma^2 = var(diff)/2,
    N = sigma / sqrt(rate)): no Allan variance involved. Within 6 % on the line-free axes."""
    doc, _, _ = mpu
    df = pd.read_csv(STATIC, skiprows=4)
    for ch, scale, to_ieee in (("gx", 250 / 32768, 60.0), ("ax", 2 / 32768, 9.80665 * 60.0)):
        sigma = np.std(np.diff(df[ch].to_numpy(float) * scale)) / np.sqrt(2.0)
        independent = sigma / np.sqrt(100.0) * to_ieee
        assert doc["channels"][ch]["coefficients"]["white"]["value"] == pytest.approx(independent, rel=0.06)


def test_real_recording_kalibr_yaml(mpu):
    doc, yaml_text, _ = mpu
    values = {}
    for line in yaml_text.splitlines():
        if line and not line.startswith("#"):
            key, rest = line.split(":", 1)
            values[key] = rest.split("#")[0].strip()
    assert set(values) >= {
        "gyroscope_noise_density",
        "gyroscope_random_walk",
        "accelerometer_noise_density",
        "accelerometer_random_walk",
        "update_rate",
    }
    white_dph = max(doc["channels"][c]["coefficients"]["white"]["value"] for c in ("gx", "gy", "gz"))
    # deg/sqrt(h) -> rad/s/sqrt(Hz): / 60 * pi / 180
    assert float(values["gyroscope_noise_density"]) == pytest.approx(white_dph / 60 * np.pi / 180, rel=1e-5)
    assert "continuous-time" in yaml_text


def test_synthesis_from_the_fitted_model_gives_back_the_measured_allan_deviation(mpu):
    """One record simulated from the real recording's fitted model, 8 times as long (so that
    its own estimation error is small beside the measured interval's): its Allan deviation at
    the measured cluster sizes lies within the measured 95 % intervals at >= 90 % of the 78
    (channel, cluster size) pairs, and >= 80 % on each channel (seeds 0-11: 95-100 % pooled,
    >= 85 % per channel). A record as long as the measured one is itself as uncertain: two
    independent estimates agree within one's 95 % interval ~83 % of the time (docs/noise.md)."""
    doc, _, _ = mpu
    model = NoiseModel.from_dict(doc)
    rate = doc["rate_hz"]
    n = 8 * int(round(doc["duration_s"] * rate))
    sim = synthesize(model, n, rate, np.random.default_rng(38))
    inside_all = []
    for name, ch in doc["channels"].items():
        m = np.rint(np.array(ch["allan"]["tau_s"]) * rate).astype(int)
        adev = allan_curve(sim[name], rate, m=m).adev
        lo, hi = np.array(ch["allan"]["adev_lo"]), np.array(ch["allan"]["adev_hi"])
        inside = (adev >= lo) & (adev <= hi)
        assert inside.mean() >= 0.8, (name, np.round(adev / np.array(ch["allan"]["adev"]), 3))
        inside_all.extend(inside)
    assert np.mean(inside_all) >= 0.9


def test_bad_input_is_one_line(tmp_path):
    if not STATIC.is_file():
        pytest.skip("no real recording")
    code, _, err = run_cli(STATIC, "--gyro-unit", "counts", "--accel-unit", "counts")
    assert code == 2 and err.count("\n") == 1 and "--gyro-range" in err
    short = tmp_path / "short.csv"
    short.write_text("gx,gy,gz,ax,ay,az\n" + "1,2,3,0,0,1\n" * 50)
    code, _, err = run_cli(short, "--rate", "100")
    assert code == 2 and err.count("\n") == 1 and "at least" in err
    code, _, err = run_cli(short)
    assert code == 2 and "--rate" in err
    code, _, err = run_cli(STATIC, *RAW[:4], "--gyro-range", "fast")
    assert code == 2 and "gyro range" in err


def test_contract_parquet_reads_like_the_csv(tmp_path):
    """A samples.parquet with the contract's metadata (raw counts, ranges): same white noise
    as the text log of the same samples."""
    if not STATIC.is_file():
        pytest.skip("no real recording")
    import pyarrow as pa
    import pyarrow.parquet as pq

    df = pd.read_csv(STATIC, skiprows=4).iloc[:20_000]
    table = pa.table({"t": np.arange(len(df)) / 100.0, **{c: df[c].to_numpy(float) for c in df.columns}})
    meta = {
        "gyro_unit": "LSB",
        "accel_unit": "LSB",
        "gyro_range_dps": "250,250,250",
        "accel_range_g": "2,2,2",
        "sample_rate_hz": "100",
    }
    pq.write_table(table.replace_schema_metadata(meta), tmp_path / "samples.parquet")
    csv = tmp_path / "log.csv"
    df.to_csv(csv, index=False)
    code, _, err = run_cli(tmp_path / "samples.parquet", "--json", tmp_path / "p.json")
    assert code == 0, err
    code, _, err = run_cli(csv, "--rate", "100", *RAW, "--json", tmp_path / "c.json")
    assert code == 0, err
    p = json.loads((tmp_path / "p.json").read_text())["channels"]
    c = json.loads((tmp_path / "c.json").read_text())["channels"]
    for ch in ("gx", "az"):
        assert p[ch]["coefficients"]["white"]["value"] == pytest.approx(
            c[ch]["coefficients"]["white"]["value"]
        )


def test_parquet_input_gets_the_fleet_readers_checks(tmp_path):
    """``mimucal noise`` reads Parquet through the dataset's noise-recording reader: a gap in
    the time column is refused in one line naming the file, as in the nightly."""
    import pyarrow as pa
    import pyarrow.parquet as pq

    rng = np.random.default_rng(3)
    t = np.arange(4000) / 100.0
    t[2000:] += 5.0  # a 5 s gap: the Allan variance needs an unbroken record
    cols = {c: rng.normal(0, 0.01, t.size) for c in ("gx", "gy", "gz", "ax", "ay")}
    table = pa.table({"t": t, **cols, "az": 1 + rng.normal(0, 1e-3, t.size)})
    meta = {"gyro_unit": "deg/s", "accel_unit": "g", "sample_rate_hz": "100"}
    pq.write_table(table.replace_schema_metadata(meta), tmp_path / "gappy.parquet")
    code, _, err = run_cli(tmp_path / "gappy.parquet")
    assert code == 2 and err.count("\n") == 1
    assert "gappy.parquet" in err and "gap" in err
