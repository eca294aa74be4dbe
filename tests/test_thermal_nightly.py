"""A nightly of a thermal lot (docs/thermal.md): the store, the calibration files (format
1.1) and the report; a unit with an out-of-limit coefficient is flagged."""

from __future__ import annotations

import json

import pandas as pd

from flows import runtime
from flows.chamber_sim import simulate_chamber_fleet

LIMITS = """
[limits]
w0_tc_x = {min = "-0.01 deg/s/degC", max = "0.01 deg/s/degC"}
w0_tc_y = {min = "-0.01 deg/s/degC", max = "0.01 deg/s/degC"}
w0_tc_z = {min = "-0.01 deg/s/degC", max = "0.01 deg/s/degC"}
"""


def test_nightly_of_a_thermal_lot(tmp_path, capsys):
    from flows import nightly

    data, results = tmp_path / "data", tmp_path / "results"
    simulate_chamber_fleet(data, lots=1, units=2, seed=7, rate_hz=25.0, out_of_limit=1)
    cfg = tmp_path / "qa.toml"
    cfg.write_text(LIMITS)
    with runtime.run_settings():
        log = nightly.nightly_flow(
            str(data), str(results), config=str(cfg), progress=False, runner="threads", run_discovery=False
        )
    assert log["units_calibrated"] == 2
    files = {p.parent.name: json.loads(p.read_text()) for p in (results / "calibrations").glob("*/*.json")}
    assert set(files) == {"U0001", "U0002"}
    for doc in files.values():
        assert doc["format_version"] == "1.1" and doc["kind"] == "thermal"
        assert doc["thermal"]["range_c"][0] < -30 and doc["thermal"]["range_c"][1] > 80
    assert files["U0001"]["qa"]["status"] == "limits" and files["U0002"]["qa"]["status"] == "pass"
    summary = pd.read_parquet(results / "tables" / "summary")
    tc = summary[(summary.model == "thermal") & (summary.parameter == "w0_tc_x")].set_index("unit")
    assert tc.loc["U0001", "flagged"] and not tc.loc["U0002", "flagged"]
    # the lot's spread of the thermal coefficients is the re-flag's (qa/T01.json), not the report's
    spread = {
        r["parameter"]: r for r in json.loads((results / "qa" / "T01.json").read_text())["thermal_spread"]
    }
    assert spread["w0_tc_x"]["n"] == 2 and spread["w0_tc_x"]["outliers"] == ["U0001 (limit)"]
    assert spread["w0_tc_x"]["min"] == tc["mean"].min() and spread["w0_tc_x"]["max"] == tc["mean"].max()
    report = (results / "reports" / "T01.html").read_text()
    assert 'id="thermal"' in report and "w0_tc_x" in report and "U0001 (limit)" in report
    assert report.count("Gyro gains K_g (diagonal), change from 25 degC") == 2  # each unit's plots
    # mimucal apply with the thermal file: in range applied per sample, out of range refused
    # in one line (exit 2) unless --extrapolate
    import pyarrow as pa
    import pyarrow.parquet as pq

    from flows.cli import main as cli_main

    cal = sorted((results / "calibrations" / "U0002").glob("*.json"))[-1]
    raw = next(data.glob("**/unit=U0002/rep=1/samples.parquet"))
    table = pq.read_table(raw)
    hot_path = tmp_path / "hot.parquet"
    i = table.schema.get_field_index("temp_c")
    pq.write_table(table.set_column(i, "temp_c", pa.compute.add(table["temp_c"], 150.0)), hot_path)
    assert cli_main(["apply", str(cal), str(raw), str(tmp_path / "ok.parquet")]) == 0
    capsys.readouterr()
    assert cli_main(["apply", str(cal), str(hot_path), str(tmp_path / "hot_out.parquet")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "outside the calibrated range" in err[0] and "--extrapolate" in err[0]
    assert not (tmp_path / "hot_out.parquet").exists()
    assert cli_main(["apply", str(cal), str(hot_path), str(tmp_path / "x.parquet"), "--extrapolate"]) == 0


def test_a_session_far_from_soaked_fails_and_leaves_the_unit():
    """Past the soak limit (10 degC over the steps) a session is an error of its own, not
    pooled, not averaged; the others make the thermal calibration."""
    from dataclasses import replace

    import numpy as np

    from calib_core.models.pipeline import calibrate_repetitions
    from calib_core.sim.chamber import chamber_schedule, thermal_physics_unit
    from flows.chamber_sim import chamber_step_means
    from flows.thermal_units import apply_thermal
    from flows.unit_pipeline import SessionOutcome, aggregate_unit

    rng = np.random.default_rng(3)
    sched = chamber_schedule(setpoints=(-20.0, 10.0, 40.0, 70.0), reps=1)
    sched[2] = replace(sched[2], soak=replace(sched[2].soak, soak_s=0.0))  # 40 degC, straight from 10
    sessions = chamber_step_means(thermal_physics_unit(rng), rng, sched)
    outcomes = []
    for s, fit in zip(sessions, calibrate_repetitions([s.sm for s in sessions])):
        sm = replace(s.sm, metadata={**s.sm.metadata, "chamber_setpoint_c": f"{s.setpoint_c:g}"})
        outcomes.append(
            SessionOutcome(sm.key, None, "ok", None, None, [], "", fit.calibration, step_means=sm)
        )
    unit_out = aggregate_unit("CH", "U000", outcomes)
    apply_thermal(unit_out, unit_out.sessions)
    bad = unit_out.sessions[2]
    assert bad.status == "failed" and bad.code == "E_NOT_SOAKED" and "rep=3" in bad.message
    assert [r.rep for r in unit_out.calibration.reps] == [1, 2, 4]
    assert unit_out.applied.kind == "thermal" and unit_out.applied.thermal is not None
