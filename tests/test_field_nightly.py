"""Field-calibrated units as a lot: recordings under ``lot=L/unit=U/field/`` found with their
options (schemas.field_dataset), calibrated by ``mimucal nightly`` into the same store, flags
and lot report as turntable units (flows.field_units), checked against the simulator's truth.

One temporary local Prefect API serves the module (PREFECT_HOME set by flows.runtime)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from flows import runtime

runtime.ensure_environment()

from calib_core.sim.hand_held import mpu6050_like_truth, simulate_hand_held  # noqa: E402
from flows.cli import main as cli_main  # noqa: E402
from schemas.dataset import find_sessions  # noqa: E402
from schemas.field_dataset import field_fingerprint, find_field_recordings  # noqa: E402
from schemas.results_store import ResultsStore  # noqa: E402
from schemas.unit_plan import plan_field_units  # noqa: E402

N_UNITS = 5
BIASED_UNIT = "H4"  # its gyro z bias is beyond the acceptance limit of the test's configuration
BIASED_Z_COUNTS = 3000.0  # 22.9 deg/s at 131 counts per deg/s


def write_log(path: Path, s) -> None:
    """A CSV log as a logger writes it: a header naming the channels, int16-like counts."""
    X = np.column_stack([s.t, s.accel, s.gyro])
    np.savetxt(path, X, delimiter=",", header="t,ax,ay,az,gx,gy,gz", comments="", fmt="%.4f")


def make_field_lot(root: Path, n_poses: int = 12) -> dict[str, object]:
    """Five simulated MPU-6050-like units, one hand-held recording each (two for H0), options
    shared by the lot (ranges, initial rest). Returns the truths by unit."""
    lot = root / "lot=F1"
    lot.mkdir(parents=True)
    (lot / "field.json").write_text(
        json.dumps({"accel_range": "2g", "gyro_range": "250dps", "init_static": 10})
    )
    truths = {}
    for u in range(N_UNITS):
        name = f"H{u}"
        truth = mpu6050_like_truth(np.random.default_rng(100 + u))
        if name == BIASED_UNIT:
            truth.gyro_bias[2] = BIASED_Z_COUNTS
        truths[name] = truth
        d = lot / f"unit={name}" / "field"
        d.mkdir(parents=True)
        for r in range(2 if u == 0 else 1):
            write_log(
                d / f"rec{r + 1}.csv",
                simulate_hand_held(
                    truth, np.random.default_rng(1000 + 10 * u + r), n_poses=n_poses, rate_hz=50.0
                ),
            )
    return truths


def stated_se(params: pd.DataFrame, model: str, names: list[str]) -> np.ndarray:
    """The stated standard error of each named parameter, the mean over the repetitions."""
    rows = params[params.model == model].set_index("parameter").loc[names]
    return rows.groupby(level=0, sort=False)["stderr"].mean().to_numpy()


# --- layout ------------------------------------------------------------------------------------
def test_field_layout_options_merge_and_errors(tmp_path):
    unit = tmp_path / "lot=L1" / "unit=U1"
    (unit / "rep=1").mkdir(parents=True)  # a turntable unit beside: its field/ is not a rep
    f = tmp_path / "lot=L1" / "unit=U2" / "field"
    f.mkdir(parents=True)
    (tmp_path / "lot=L1" / "field.json").write_text(json.dumps({"gyro_unit": "rad/s", "rate": 100}))
    (f / "field.json").write_text(json.dumps({"rate": 50}))
    (f / "b.csv").write_text("1\n")
    (f / "a.csv").write_text("1\n")
    (f / "a.csv.json").write_text(json.dumps({"rate": 200, "accel_unit": "m/s^2"}))
    pair = f / "c"
    pair.mkdir()
    (pair / "acc.txt").write_text("0 1 2 3\n")
    (pair / "gyro.txt").write_text("0 1 2 3\n")
    (f / "d").mkdir()  # a directory that is not an IMU-TK pair
    refs, errors = find_field_recordings(tmp_path)
    assert [(r.key.unit, r.key.rep, r.name) for r in refs] == [
        ("U2", 1, "a.csv"),
        ("U2", 2, "b.csv"),
        ("U2", 3, "c"),
    ]
    a, b, c = refs
    assert (a.options["rate"], a.options["accel_unit"], a.options["gyro_unit"]) == (200, "m/s^2", "rad/s")
    assert (b.options["rate"], b.options["accel_unit"]) == (50, "LSB")  # the unit's file over the lot's
    assert c.files == (pair / "acc.txt", pair / "gyro.txt")
    assert len(errors) == 1 and errors[0].code == "E_BAD_PATH" and "IMU-TK's pair" in str(errors[0])
    # the turntable finder does not take field/ for a badly named rep directory
    (unit / "field").mkdir()
    _, terr = find_sessions(tmp_path)
    assert not [e for e in terr if "field" in str(e)]
    # an unknown option names the file; the unit's recordings fail by name with it
    (f / "field.json").write_text(json.dumps({"rates": 50}))
    refs, errors = find_field_recordings(tmp_path)
    assert refs and all(r.error is not None and r.error.code == "E_BAD_OPTION" for r in refs)
    assert "unknown option 'rates'" in str(refs[0].error) and "field.json" in str(refs[0].error)
    # a changed option changes the recording's fingerprint
    (f / "field.json").write_text(json.dumps({"rate": 50}))
    refs, _ = find_field_recordings(tmp_path)
    fp = field_fingerprint(refs[1])
    (f / "field.json").write_text(json.dumps({"rate": 60}))
    assert field_fingerprint(find_field_recordings(tmp_path)[0][1]) != fp


def test_unit_with_turntable_sessions_and_field_recordings_is_not_calibrated_twice(tmp_path):
    f = tmp_path / "lot=L1" / "unit=U1" / "field"
    f.mkdir(parents=True)
    (f / "a.csv").write_text("1\n")
    jobs, skipped, errors = plan_field_units(tmp_path, {}, turntable_units={"U1"})
    assert not jobs and not skipped
    assert "turntable sessions (rep=N) and field recordings" in str(errors[0])


# --- a lot of five field-calibrated units through the nightly ----------------------------------
@pytest.mark.slow
def test_field_lot_through_nightly(tmp_path):
    data, results = tmp_path / "data", tmp_path / "results"
    truths = make_field_lot(data)
    cfg = tmp_path / "limits.toml"
    cfg.write_text('[limits]\nw0_z = {min = "-15 deg/s", max = "15 deg/s"}\n')
    rc = cli_main(
        [
            "nightly",
            str(data),
            "--results",
            str(results),
            "--config",
            str(cfg),
            "--runner",
            "threads",
            "--quiet",
        ]
    )
    assert rc in (0, 1)  # 1: a unit is flagged
    store = ResultsStore(results)
    units = store.read("units").set_index("unit")
    assert sorted(units.index) == [f"H{u}" for u in range(N_UNITS)]
    assert (units["state"] == "calibrated").all()
    # flags: exactly the unit whose gyro bias is beyond the limit
    assert units.loc[BIASED_UNIT, "flagged"] and "w0_z" in units.loc[BIASED_UNIT, "flag_reason"]
    assert not units.drop(BIASED_UNIT)["flagged"].any()
    # averages and spreads: H0's two recordings are its repetitions
    summary = store.read("summary")
    k11 = summary[(summary.unit == "H0") & (summary.parameter == "k_g11")].iloc[0]
    assert k11["n_reps"] == 2 and k11["std"] > 0
    assert set(summary["model"]) == {"gyro", "accel", "field_fit"}
    # each unit's applied calibration (kind field) against the simulator's truth, within 5
    # stated standard errors (the stated errors are ~1.3x optimistic, docs/real-data.md)
    params = store.read("parameters")
    for name, truth in truths.items():
        doc = json.loads((results / units.loc[name, "calibration_file"]).read_text())
        assert doc["kind"] == "field"
        K_g = np.asarray(doc["K_g"])
        K_a = np.asarray(doc["K_a"])
        w0 = np.asarray(doc["w0"])
        true_K_g = np.degrees(truth.gyro_matrix)
        true_K_a = truth.accel_matrix / truth.g_local
        p = params[params.unit == name]
        kg_names = [f"k_g{i}{j}" for i in (1, 2, 3) for j in (1, 2, 3)]
        ka_names = [f"k_a{i}{j}" for i in (1, 2, 3) for j in (1, 2, 3)]
        assert np.all(np.abs(K_g - true_K_g).ravel() <= 5 * stated_se(p, "gyro", kg_names) + 1e-12), name
        assert np.all(np.abs(K_a - true_K_a).ravel() <= 5 * stated_se(p, "accel", ka_names) + 1e-15), name
        true_w0 = -true_K_g @ truth.gyro_bias
        assert np.all(np.abs(w0 - true_w0) <= 5 * stated_se(p, "gyro", ["w0_x", "w0_y", "w0_z"]) + 1e-9), name
        # and the calibration is a real gain: the scales are 2 % off nominal before
        assert np.max(np.abs(K_g - true_K_g)) < 0.1 * np.max(np.abs(np.diag(true_K_g) - 1 / 131.072))
    # model discovery ran on the static poses of each unit (one row per unit at least)
    disc = store.read("discovery")
    assert set(disc["unit"]) == set(truths)
    assert disc["advice"].str.contains("static poses of field recording").all()
    # the lot report lists the five units
    html = (results / "reports" / "F1.html").read_text()
    assert all(f"H{u}" in html for u in range(N_UNITS))
    sessions = store.read("sessions")
    assert len(sessions) == N_UNITS + 1 and sessions["path"].str.contains("/field/rec").all()

    # unchanged recordings are skipped; a recording made unreadable fails its unit, which keeps
    # its last good calibration (stale), naming the recording's file
    (data / "lot=F1" / "unit=H2" / "field" / "rec1.csv").write_text("garbage,1,2\n")
    cli_main(["nightly", str(data), "--results", str(results), "--runner", "threads", "--quiet"])
    units2 = store.read("units").set_index("unit")
    assert units2.loc["H2", "state"] == "stale"
    assert units2.loc["H2", "calibration_file"] == units.loc["H2", "calibration_file"]
    assert (units2.drop("H2")["run_id"] == units.drop("H2")["run_id"]).all()  # not recalibrated
    s2 = store.read("sessions")
    msg = s2[(s2.unit == "H2")]["message"].iloc[0]
    assert "E_UNREADABLE_FILE" in msg and "rec1.csv" in msg and "unit=H2" in msg
    assert isinstance(pd.Timestamp(units2.loc["H2", "updated_at"]), pd.Timestamp)

    # a field unit is rerun alone: recalibrated (new run id), its unit report written
    assert cli_main(["rerun", str(data), "--results", str(results), "--unit", "H1"]) in (0, 1)
    units3 = store.read("units").set_index("unit")
    assert units3.loc["H1", "run_id"] != units2.loc["H1", "run_id"]
    assert units3.loc["H1", "state"] == "calibrated"
    assert (results / "reports" / "units" / "H1.html").is_file()


def test_recordings_in_other_raw_units_than_the_first_fail_by_name():
    from types import SimpleNamespace

    from calib_core.steps import SessionKey
    from flows.field_units import drop_mixed_units
    from flows.unit_pipeline import SessionOutcome

    def outcome(rep, gyro_unit):
        fits = {"gyro": SimpleNamespace(raw_unit=gyro_unit), "accel": SimpleNamespace(raw_unit="LSB")}
        cal = SimpleNamespace(fits=fits)
        return SessionOutcome(SessionKey("L", "U", rep), Path(f"r{rep}.csv"), "ok", None, None, [], "", cal)

    outs = [outcome(1, "LSB"), outcome(2, "deg/s"), outcome(3, "LSB")]
    kept_outs, kept = drop_mixed_units(outs, ["fit1", "fit2", "fit3"])
    assert kept == ["fit1", "fit3"]
    assert [o.status for o in kept_outs] == ["ok", "failed", "ok"]
    assert kept_outs[1].code == "E_MIXED_UNITS" and "r2.csv" in kept_outs[1].message
    assert "r1.csv" in kept_outs[1].message


def test_numeric_options_take_the_command_lines_fractions(tmp_path):
    """``"gyro_scale": "1/6258"`` in an options file means what ``--gyro-scale 1/6258`` means;
    a string that is no number is an error naming the file and the option."""
    f = tmp_path / "lot=L1" / "unit=U1" / "field"
    f.mkdir(parents=True)
    (f / "a.csv").write_text("1\n")
    (f / "field.json").write_text(json.dumps({"gyro_scale": "1/6258", "acc_bias": "32768"}))
    (ref,), errors = find_field_recordings(tmp_path)
    assert not errors
    assert ref.options["gyro_scale"] == 1 / 6258 and ref.options["acc_bias"] == 32768.0
    (f / "field.json").write_text(json.dumps({"gyro_scale": "fast"}))
    (ref,), errors = find_field_recordings(tmp_path)
    assert not errors and "option 'gyro_scale' is not a number ('fast')" in str(ref.error)
    assert "field.json" in str(ref.error)
