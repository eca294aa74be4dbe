"""The Python API (schemas.api, issue 20 item 6): its docstring examples, the README's
example, loading from a results folder by date, the unit checks, discovery on a unit with a
known effect, and the same numbers as the CLI."""

from __future__ import annotations

import doctest
import json
import re
import subprocess
import sys
from datetime import UTC, datetime, timedelta
from pathlib import Path

import numpy as np
import pytest

import schemas.api as api
from schemas.calibration_file import CalibrationFileError

ROOT = Path(__file__).resolve().parent.parent


def test_docstring_examples_run():
    res = doctest.testmod(api, optionflags=doctest.ELLIPSIS)
    assert res.attempted >= 20 and res.failed == 0


@pytest.mark.slow
def test_readme_example_runs(tmp_path):
    text = (ROOT / "README.md").read_text()
    section = text[text.index("## Python API") :]
    code = re.search(r"```python\n(.*?)```", section, re.S).group(1)
    out = subprocess.run(
        [sys.executable, "-c", code],
        capture_output=True,
        text=True,
        cwd=tmp_path,
        timeout=300,
        env={"PYTHONPATH": str(ROOT), "PATH": ""},
    )
    assert out.returncode == 0, out.stderr
    assert "w_x" in out.stdout and out.stdout.rstrip().endswith("[]")


@pytest.fixture(scope="module")
def unit(tmp_path_factory):
    root = tmp_path_factory.mktemp("api")
    truth = api.simulate_unit_dataset(root / "data", unit="U0007", reps=3, seed=5, rate_hz=10)
    return root, truth, api.calibrate_unit(root / "data", "U0007", discover=False)


def assert_same_numbers(a, b, where: str) -> None:
    """``a == b`` for JSON values, floats to 1e-9 relative (an ill-conditioned fit such as
    the lever arm moves its last digits with the BLAS kernel)."""
    if isinstance(a, float) or isinstance(b, float):
        assert a == pytest.approx(b, rel=1e-9, abs=1e-12), where
    elif isinstance(a, dict):
        assert isinstance(b, dict) and a.keys() == b.keys(), where
        for key in a:
            assert_same_numbers(a[key], b[key], f"{where}.{key}")
    elif isinstance(a, list):
        assert isinstance(b, list) and len(a) == len(b), where
        for i, (x, y) in enumerate(zip(a, b)):
            assert_same_numbers(x, y, f"{where}[{i}]")
    else:
        assert a == b, where


def test_calibrate_unit_recovers_the_truth_and_equals_the_cli(unit, tmp_path):
    root, truth, res = unit
    assert res.n_reps == 3 and res.failed == [] and res.lot == "L01"
    assert np.abs(res.calibration.K_g - truth.K_g).max() < 1e-3
    assert np.abs(res.calibration.K_a - truth.K_a).max() < 1e-3
    path = tmp_path / "cli.json"
    out = subprocess.run(
        [
            sys.executable,
            "-m",
            "flows.cli",
            "calibrate",
            str(root / "data"),
            "--unit",
            "U0007",
            "--json",
            str(path),
            "--no-discovery",
        ],
        capture_output=True,
        text=True,
        env={"PYTHONPATH": str(ROOT)},
        timeout=300,
    )
    assert out.returncode == 0, out.stderr
    cli = json.loads(path.read_text())
    mine = json.loads(res.save(tmp_path / "api.json").read_text())
    # the same fit in another process: equal up to the last bits BLAS may order differently
    # (OpenBLAS picks its kernels and threads per machine and process)
    for k in ("format", "format_version", "K_g", "w0", "K_a", "f0", "terms", "raw_units"):
        assert_same_numbers(cli[k], mine[k], k)
    assert_same_numbers(cli["repetitions"], mine["repetitions"], "repetitions")


def test_load_from_a_results_folder_by_date_and_the_unit_checks(unit, tmp_path):
    from schemas.results_store import ResultsStore

    root, truth, res = unit
    store = ResultsStore(tmp_path / "results")
    old = res.calibration.__class__(**{**res.calibration.__dict__, "w0": res.calibration.w0 + 1.0})
    t1 = datetime(2026, 11, 20, 12, tzinfo=UTC)
    store.save_calibration(old, "U0007", {}, t1)
    store.save_calibration(res.calibration, "U0007", {}, t1 + timedelta(days=2))
    got = api.load_calibration_for(store.root, unit="U0007", at="2026-11-21")
    assert np.allclose(got.w0, old.w0)
    got = api.load_calibration_for(store.root, unit="U0007", at="2026-11-23T00:00:00Z")
    assert np.allclose(got.w0, res.calibration.w0)
    got = api.load_calibration_for(store.root, unit="U0007")  # now: the latest
    assert np.allclose(got.w0, res.calibration.w0)
    with pytest.raises(LookupError):
        api.load_calibration_for(store.root, unit="U0007", at="2026-11-19")
    with pytest.raises(LookupError):
        api.load_calibration_for(store.root, unit="U9999")
    f = res.save(tmp_path / "U0007.json")
    with pytest.raises(api.CalibrationMismatch, match="unit U0007, not U0001"):
        api.load_calibration_for(f, unit="U0001")
    (tmp_path / "x.json").write_text('{"format": "something"}')
    with pytest.raises(CalibrationFileError):
        api.load_calibration_for(tmp_path / "x.json")


def test_apply_to_frame_converts_named_units_and_refuses_mismatches(unit):
    root, truth, res = unit
    raw = api.read_samples(root / "data/lot=L01/unit=U0007/rep=1/samples.parquet")
    ref = api.apply_to_frame(res.calibration, raw)
    # the same samples in rad/s and m/s^2 give the same calibrated values
    si = raw.astype({c: "float64" for c in ("gx", "gy", "gz", "ax", "ay", "az")})
    si[["gx", "gy", "gz"]] *= np.pi / 180
    si[["ax", "ay", "az"]] *= float(raw.attrs["g_local"])
    si.attrs = {"unit": "U0007", "g_local": raw.attrs["g_local"]}
    with pytest.raises(ValueError, match="name the raw units"):
        api.apply_to_frame(res.calibration, si)
    conv = api.apply_to_frame(res.calibration, si, gyro_unit="rad/s", accel_unit="m/s^2")
    assert np.allclose(conv.to_numpy(float), ref.to_numpy(float), rtol=1e-10, atol=1e-12)
    assert conv.attrs["gyro_unit"] == "deg/s" and conv.attrs["accel_unit"] == "g"
    with pytest.raises(api.CalibrationMismatch, match="raw_units"):
        api.apply_to_frame(res.calibration, raw, accel_unit="LSB")
    with pytest.raises(api.CalibrationMismatch, match="unit U0001, the calibration of unit U0007"):
        api.apply_to_frame(res.calibration, raw, unit="U0001")
    with pytest.raises(ValueError, match="missing column"):
        api.apply_to_frame(res.calibration, raw.drop(columns=["gz"]))
    # at rest the calibrated rate is the truth's (earth rate aside: below the noise)
    at_rest = ref[raw["step"] == 0]
    assert np.abs(at_rest[["w_x", "w_y", "w_z"]].mean().to_numpy()).max() < 0.05


def test_discover_unit_names_an_effect_put_into_the_simulation(tmp_path):
    """A gyro scale nonlinearity put into the simulated unit is named; a linear unit gets
    none (the README example's [] is checked in test_readme_example_runs)."""
    from calib_core.effects import get_effect
    from calib_core.sim.protocols import default_session
    from calib_core.sim.simulator import (
        draw_repetition_truth,
        session_metadata,
        simulate_session,
        typical_truth,
    )
    from calib_core.steps import SessionKey
    from schemas.writer import write_session

    rng = np.random.default_rng(21)
    # z gyro cubic scale error: 0.3 deg/s at 1000 deg/s (as tests/test_flows_extended_residuals)
    truth = typical_truth(rng, gyro_noise_dps=0.05, gyro_bias_instability_dps=0.005).with_effects(
        (get_effect("gyro_scale_nonlinearity"), np.array([0, 0, 0, 0, 0, 0.3]))
    )
    steps = default_session()
    for rep in (1, 2, 3):
        rt = draw_repetition_truth(truth, rng)
        write_session(
            tmp_path,
            SessionKey("L01", "U0001", rep),
            steps,
            simulate_session(rt, steps, rng, 20.0),
            session_metadata(rt, 20.0, lot="L01", unit="U0001", rep=str(rep)),
        )
    d = api.discover_unit(tmp_path, "U0001").to_dict()
    assert [e["name"] for e in d["effects"]] == ["gyro_scale_nonlinearity"]
    res = api.calibrate_unit(tmp_path, "U0001")  # discovery's calibration is the one applied
    assert [t.name for t in res.calibration.terms] == ["gyro_scale_nonlinearity"]
    assert abs(res.calibration.terms[0].params[5] - 0.3) < 0.05


def test_calibrate_unit_names_a_bad_session_and_leaves_out_a_contradicting_step(tmp_path):
    """As the nightly: a truncated samples file is a failed entry (not an exception), and a
    step that contradicts the same step in the other repetitions is left out with
    W_INCONSISTENT_STEP, its session 'warned'."""
    import pyarrow as pa
    import pyarrow.parquet as pq

    data = tmp_path / "data"
    api.simulate_unit_dataset(data, unit="U0003", reps=4, seed=2, rate_hz=10)
    reps = sorted((data / "lot=L01" / "unit=U0003").iterdir())
    (reps[3] / "samples.parquet").write_bytes((reps[3] / "samples.parquet").read_bytes()[:100])
    table = pq.read_table(reps[1] / "samples.parquet")
    ax = table.column("ax").to_numpy().astype(np.float64)
    ax[np.flatnonzero(table.column("step").to_numpy() == 80)[-5:]] += 0.5  # 5 samples, in range
    pq.write_table(
        table.set_column(table.schema.get_field_index("ax"), "ax", pa.array(ax)), reps[1] / "samples.parquet"
    )
    res = api.calibrate_unit(data, "U0003", discover=False)
    assert [(f["rep"], f["code"]) for f in res.failed] == [(4, "E_UNREADABLE_FILE")]
    status = {s["rep"]: (s["status"], s["warnings"]) for s in res.sessions}
    assert status[1] == ("ok", []) and status[3] == ("ok", [])
    assert status[2][0] == "warned" and len(status[2][1]) == 1
    assert status[2][1][0].startswith("[W_INCONSISTENT_STEP] lot=L01/unit=U0003/rep=2: step 80 (")
    assert "ax differs from the same step in the unit's other repetitions" in status[2][1][0]
