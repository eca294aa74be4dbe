"""Noise in the fleet run, the parts that need no noise analysis: the noise recordings'
contract (hostile input refused with one line naming the recording, the file and the
reason), noise limits in engineering units, and the lot's noise judgement on rows whose
truth is known."""

from __future__ import annotations

import math
import os

import numpy as np
import pandas as pd
import pytest

from calib_core.noise_fleet import judge_noise, static_step_record
from calib_core.outliers import ThresholdTable
from calib_core.sim.noise_recording import static_noise_recording
from calib_core.sim.simulator import MimuTruth
from schemas.dataset import find_sessions
from schemas.errors import SessionError
from schemas.limits import LimitsError, config_from_toml
from schemas.noise_dataset import find_noise_recordings, read_noise_recording
from schemas.writer import write_noise_recording

MD = {"gyro_unit": "deg/s", "accel_unit": "g", "gyro_range_dps": "300,300,300", "accel_range_g": "8,8,8"}


def _recording(n=1000, rate=50.0, seed=1):
    return static_noise_recording(MimuTruth(), n / rate, rate, np.random.default_rng(seed))


@pytest.fixture
def unit_dir(tmp_path):
    write_noise_recording(tmp_path, "L1", "U1", "good", _recording(), {**MD, "sample_rate_hz": "50"})
    return tmp_path / "lot=L1" / "unit=U1"


def test_a_good_recording_reads_with_its_rate_and_units(unit_dir):
    refs, errors = find_noise_recordings(unit_dir, "L1", "U1")
    assert [r.name for r in refs] == ["good"] and errors == []
    rec = read_noise_recording(refs[0])
    assert rec.rate_hz == 50.0 and rec.gyro.shape == (1000, 3) and rec.duration_s == pytest.approx(20.0)
    # z up at rest: the accelerometer reads 1 g on z (the default truth is the identity)
    assert rec.accel[:, 2].mean() == pytest.approx(1.0, abs=1e-3)


def test_a_noise_directory_is_no_session_and_no_bad_path(unit_dir):
    refs, errors = find_sessions(unit_dir.parent.parent)
    assert refs == [] and errors == []


def test_hostile_entries_are_refused_one_line_each(unit_dir, tmp_path):
    nd = unit_dir / "noise"
    (nd / "notes.txt").write_text("hello")  # not <name>.parquet
    (nd / "bad name.parquet").write_bytes(b"x")  # not an id
    (nd / "empty.parquet").write_bytes(b"")
    outside = tmp_path / "elsewhere.parquet"
    outside.write_bytes((nd / "good.parquet").read_bytes())
    os.symlink(outside, nd / "linked.parquet")
    os.mkfifo(nd / "fifo.parquet")
    (nd / ".hidden.parquet").write_bytes(b"")  # ignored
    refs, errors = find_noise_recordings(unit_dir, "L1", "U1")
    assert sorted(r.name for r in refs) == ["empty", "good"]
    by_file = {e.file: e for e in errors}
    assert set(by_file) == {"notes.txt", "bad name.parquet", "linked.parquet", "fifo.parquet"}
    assert "--follow-symlinks" in str(by_file["linked.parquet"])
    assert by_file["fifo.parquet"].code == "E_UNREADABLE_FILE"
    for e in errors:
        assert "\n" not in str(e) and "lot=L1/unit=U1/noise" in str(e)
    with pytest.raises(SessionError, match=r"lot=L1/unit=U1/noise/empty.*empty \(0 bytes\)"):
        read_noise_recording(next(r for r in refs if r.name == "empty"))
    # with --follow-symlinks the link is read
    refs, errors = find_noise_recordings(unit_dir, "L1", "U1", follow_symlinks=True)
    assert "linked" in [r.name for r in refs]


def test_a_linked_noise_directory_needs_follow_symlinks(tmp_path):
    real = tmp_path / "real"
    write_noise_recording(real, "L1", "U1", "a", _recording(), MD)
    unit = tmp_path / "data" / "lot=L1" / "unit=U1"
    unit.mkdir(parents=True)
    os.symlink(real / "lot=L1" / "unit=U1" / "noise", unit / "noise")
    refs, errors = find_noise_recordings(unit, "L1", "U1")
    assert refs == [] and len(errors) == 1 and "symbolic link" in str(errors[0])
    refs, errors = find_noise_recordings(unit, "L1", "U1", follow_symlinks=True)
    assert [r.name for r in refs] == ["a"] and errors == []


@pytest.mark.parametrize(
    "damage, code, words",
    [
        ("gap", "E_NONINCREASING_TIME", "not uniformly sampled"),
        ("nan", "E_NONFINITE_VALUE", "gy is not finite at row 7"),
        ("short", "E_EMPTY_SESSION", "at least 256"),
        ("no_gz", "E_MISSING_COLUMN", "'gz'"),
        ("metadata", "E_BAD_METADATA", "gyro_range_dps"),
    ],
)
def test_bad_content_is_one_line_naming_recording_and_file(tmp_path, damage, code, words):
    df, md = _recording(), dict(MD)
    if damage == "gap":
        df.loc[500:, "t"] += 1.0
    elif damage == "nan":
        df.loc[7, "gy"] = np.nan
    elif damage == "short":
        df = df.iloc[:100]
    elif damage == "no_gz":
        df = df.drop(columns="gz").assign(gz=0.0)
    elif damage == "metadata":
        del md["gyro_range_dps"]
    path = write_noise_recording(tmp_path, "L1", "U1", "r", df, md)
    if damage == "no_gz":  # written with gz, then rewritten without it
        import pyarrow.parquet as pq

        t = pq.read_table(path)
        pq.write_table(t.drop(["gz"]), path)
    refs, _ = find_noise_recordings(path.parent.parent, "L1", "U1")
    with pytest.raises(SessionError) as err:
        read_noise_recording(refs[0])
    text = str(err.value)
    assert err.value.code == code and words in text and "lot=L1/unit=U1/noise/r" in text and "\n" not in text


def test_noise_limits_convert_engineering_units_to_the_stored_ones():
    cfg = config_from_toml(
        "[limits]\n"
        'gyro_white = {max = "0.005 deg/s/sqrt(Hz)"}\n'  # = 0.3 deg/sqrt(h)
        'gyro_bias_instability = {max = "0.001 deg/s"}\n'  # = 3.6 deg/h
        'accel_white = {max = "0.1 mg/sqrt(Hz)"}\n'
        'accel_bias_instability = {max = "0.0098 m/s^2"}\n'
    )
    got = {lim.parameter: (lim.max, lim.unit) for lim in cfg.limits}
    assert got["gyro_white"][0] == pytest.approx(0.3) and got["gyro_white"][1] == "deg/sqrt(h)"
    assert got["gyro_bias_instability"] == (pytest.approx(3.6), "deg/h")
    # 0.1 mg/sqrt(Hz) = 9.80665e-4 m/s^2/sqrt(Hz) = 9.80665e-4 * 60 m/s/sqrt(h)
    assert got["accel_white"] == (pytest.approx(9.80665e-4 * 60), "m/s/sqrt(h)")
    assert got["accel_bias_instability"] == (pytest.approx(0.0098 / 9.80665 * 1e3), "mg")
    with pytest.raises(LimitsError, match="valid units for gyro white"):
        config_from_toml('[limits]\ngyro_white = {max = "0.3 deg/h"}\n')
    with pytest.raises(LimitsError, match="no unit"):
        config_from_toml("[limits]\ngyro_white = {max = 0.3}\n")


def _lot_rows(rng, n_units=10, noisy=None, factor=3.0, rel_sd=0.05, rel_ci=0.03):
    """A lot's noise rows: every unit's gyro white coefficients log-normal about 0.3
    deg/sqrt(h) (unit-to-unit spread rel_sd), a bias instability poorly determined (its
    interval a factor 2 wide, its estimate as scattered), ``noisy`` with ``factor`` times
    the white noise."""
    rows = []
    for i in range(n_units):
        u = f"U{i + 1:02d}"
        for ch in ("gx", "gy", "gz"):
            v = 0.3 * math.exp(rng.normal(0, rel_sd)) * (factor if u == noisy else 1.0)
            e = v * math.exp(rng.normal(0, rel_ci))
            rows.append(
                dict(
                    lot="L1",
                    unit=u,
                    channel=ch,
                    coefficient="white",
                    value=e,
                    lo=e / 1.06,
                    hi=e * 1.06,
                    unit_of_measure="deg/sqrt(h)",
                )
            )
            b = 5.0 * math.exp(rng.normal(0, math.log(2) / 1.96))
            rows.append(
                dict(
                    lot="L1",
                    unit=u,
                    channel=ch,
                    coefficient="bias_instability",
                    value=b,
                    lo=b / 2,
                    hi=b * 2,
                    unit_of_measure="deg/h",
                )
            )
    return pd.DataFrame(rows)


def test_judge_noise_flags_the_noisy_unit_only_and_says_why():
    thresholds = ThresholdTable()
    clean_flags = 0
    for seed in range(20):
        rng = np.random.default_rng(seed)
        out, flags, _ = judge_noise(_lot_rows(rng, noisy="U04"), thresholds=thresholds)
        assert {f.unit for f in flags} == {"U04"}, seed
        assert all("white" in f.reason and "lot median" in f.reason for f in flags)
        assert out.loc[out["flagged"], "unit"].unique().tolist() == ["U04"]
        clean_out, clean, _ = judge_noise(_lot_rows(np.random.default_rng(100 + seed)), thresholds=thresholds)
        clean_flags += bool(clean)
    assert clean_flags <= 1  # family-wise alpha 1 % per lot


def test_judge_noise_limits_in_the_stored_unit():
    cfg = config_from_toml('[limits]\ngyro_white = {max = "0.4 deg/sqrt(h)"}\n')
    rows = _lot_rows(np.random.default_rng(3), n_units=3, noisy="U02", factor=2.0)  # too few units for z
    out, flags, note = judge_noise(rows, cfg.limits)
    assert {f.unit for f in flags} == {"U02"} and all(f.kind == "limit" for f in flags)
    assert "fewer than 5" in note
    cfg = config_from_toml('[limits]\ngyro_white = {max = "0.4 deg/s/sqrt(Hz)"}\n')  # 24 deg/sqrt(h)
    assert not judge_noise(rows, cfg.limits)[1]


def test_static_step_record_removes_each_steps_mean():
    rng = np.random.default_rng(0)
    segs = [rng.normal(0, 1, (50, 6)) + rng.normal(0, 100, 6) for _ in range(8)] + [np.zeros((3, 6))]
    rec, shortest = static_step_record(segs)
    assert rec.shape == (400, 6) and shortest == 50
    assert np.abs(rec.reshape(8, 50, 6).mean(axis=1)).max() < 1e-9


def test_simulate_noise_options_refuse_what_they_cannot_do(tmp_path, capsys):
    from flows.cli import main

    bad = tmp_path / "bad.json"
    bad.write_text('{"rate_hz": 1, "duration_s": 1, "channels": {"gx": {"unit": "furlong"}}}')
    cases = [
        (["--physics", "--noise-recordings", "10"], "not --physics"),
        (["--noise-from", str(bad), "--noise-recordings", "10"], "channel gx"),
        (["--noise-from", str(tmp_path / "none.json")], "none.json"),
        (["--noisy-units", "5", "--units", "2"], "noisy_units=5"),
    ]
    for i, (args, words) in enumerate(cases):
        assert main(["simulate", str(tmp_path / f"out{i}"), *args]) == 2
        err = capsys.readouterr().err.strip()
        assert words in err and "\n" not in err, err
