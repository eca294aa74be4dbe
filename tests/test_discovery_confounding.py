"""Confounded effects, the Earth rate and the thermal terms on the independent physics
simulator (small seeded samples of the figures in docs/model-discovery.md), the location
metadata and heading_deg through the reader, and the Earth rate never removed by a
calibration."""

from __future__ import annotations

import numpy as np
import pytest

from calib_core.calibration import Calibration, TermValue
from calib_core.discovery import diagnose_unit
from calib_core.effects import get_effect
from calib_core.effects.earth_rate import EARTH_RATE_DEG_H
from calib_core.sim import protocols
from calib_core.sim.physics import Turntable, typical_physics_unit
from flows.commands.diagnose import summary_lines
from schemas.averaging import read_step_means
from schemas.contract import parse_metadata
from schemas.dataset import find_sessions
from schemas.errors import SessionError
from schemas.physics_sessions import physics_unit_step_means, write_physics_unit
from schemas.reader import validate_steps
from tools.discovery_evaluation_ident import earth_rate_scenario, quiet_gyros, sensor_effect_scenario


def step_means_of(unit, steps, rng, unit_id, table):
    return physics_unit_step_means(unit, steps, rng, n_reps=5, unit_id=unit_id, table=table or Turntable())


@pytest.mark.slow
def test_whole_turns_report_earth_rate_confounded_never_one_name():
    o = earth_rate_scenario(step_means_of, protocols.whole_turn_session(), 4, seed=11)
    assert o.named == 0 and o.other_named == 0, o.notes  # never one of them alone
    assert o.confounded >= 3, o.notes


@pytest.mark.slow
def test_two_headings_name_earth_rate_alone_with_the_right_size():
    steps = protocols.extended(protocols.whole_turn_session(), protocols.two_heading_stationary())
    o = earth_rate_scenario(step_means_of, steps, 4, seed=12)
    assert o.named_alone == 4, o.notes
    assert o.within_2se >= 3


@pytest.mark.slow
def test_confounded_diagnosis_prints_the_group_and_the_advice():
    rng = np.random.default_rng(3)
    unit = quiet_gyros(typical_physics_unit(rng))
    d = diagnose_unit(
        step_means_of(unit, protocols.whole_turn_session(), rng, "U", Turntable(latitude_deg=45.0)),
        tables=False,
    )
    assert [c.terms for c in d.confounded] == [("earth_rate", "gyro_g_sensitivity")]
    assert d.effects == []
    text = "\n".join(summary_lines(d))
    assert "confounded: [earth_rate, gyro_g_sensitivity] (combined fit applied; none named)" in text
    assert "stationary steps at two headings" in text
    # the combined fit is applied: both terms are in the unit's calibration
    assert {t.name for t in d.terms} >= {"earth_rate", "gyro_g_sensitivity"}


@pytest.mark.slow
def test_location_metadata_through_the_reader_pins_the_earth_rate(tmp_path):
    rng = np.random.default_rng(5)
    unit = quiet_gyros(typical_physics_unit(rng))
    table = Turntable(latitude_deg=45.0, heading_deg=130.0, declare_location=True)
    write_physics_unit(tmp_path, unit, protocols.default_session(), rng, n_reps=4, table=table)
    refs, errors = find_sessions(tmp_path)
    assert not errors
    sms = [read_step_means(r)[0] for r in refs]
    assert all(sm.latitude_deg == 45.0 and sm.table_heading_deg == 130.0 for sm in sms)
    assert all(sm.settle_s is not None for sm in sms)
    d = diagnose_unit(sms, tables=False)
    assert [e.name for e in d.effects] == ["earth_rate"] and not d.confounded
    e = d.effects[0]
    # pinned: one free parameter, the others not excited
    assert set(e.undetermined) == {"omega_h1", "omega_h2"}
    truth = EARTH_RATE_DEG_H * np.sin(np.radians(45.0))
    assert abs(e.estimate["omega_up"] - truth) < 3 * e.stderr["omega_up"]


@pytest.mark.slow
def test_thermal_scale_drift_named_with_its_sensor():
    o = sensor_effect_scenario(step_means_of, protocols.default_session(), "thermal_scale_drift", 4, seed=21)
    assert o.named >= 3 and o.other_named == 0, o.notes
    assert o.right_axis == o.named


def test_heading_column_and_location_metadata_are_validated():
    steps = protocols.zhang2017_session().assign(heading_deg=90.0)
    assert (validate_steps(steps, "s")["heading_deg"] == 90.0).all()
    with pytest.raises(SessionError, match="heading_deg is nan"):
        validate_steps(steps.assign(heading_deg=np.nan), "s")
    md = {"gyro_unit": "deg/s", "accel_unit": "g", "gyro_range_dps": "300", "accel_range_g": "16"}
    meta = parse_metadata({**md, "latitude_deg": "45.5", "table_heading_deg": "-10"}, "s")
    assert (meta.latitude_deg, meta.table_heading_deg) == (45.5, -10.0)
    assert parse_metadata(md, "s").latitude_deg is None
    with pytest.raises(SessionError, match="latitude_deg"):
        parse_metadata({**md, "latitude_deg": "95"}, "s")


def test_a_calibration_never_removes_the_earth_rate():
    """The Earth's rotation is signal once the unit leaves the table: applying a calibration
    with an earth_rate term leaves the outputs as the affine part makes them."""
    cal = Calibration(
        K_g=np.eye(3),
        w0=np.zeros(3),
        K_a=np.eye(3),
        f0=np.zeros(3),
        terms=(TermValue("earth_rate", np.array([10.6, 3.0, 1.0]), np.array([0.4, 0.5, 0.5]), {}),),
    )
    G = np.array([[0.1, 0.2, 0.3]])
    A = np.array([[0.0, 0.0, 1.0]])
    w, f = cal.apply(G, A)
    assert np.allclose(w, G) and np.allclose(f, A)


@pytest.mark.slow
def test_nightly_stores_findings_and_their_evidence_and_the_report_draws_it(tmp_path):
    from flows import runtime

    runtime.ensure_environment()
    from flows.cli import main as cli_main
    from reports.lot import write_lot_report
    from schemas.results_store import ResultsStore

    data, results = tmp_path / "data", tmp_path / "results"
    rng = np.random.default_rng(2118)
    unit, _, _ = get_effect("lever_arm").hide(typical_physics_unit(rng), rng)
    write_physics_unit(
        data, unit, protocols.default_session(), rng, n_reps=3, rate_hz=20.0, lot="EV", unit_id="U0"
    )
    assert cli_main(["nightly", str(data), "--results", str(results)]) == 0
    store = ResultsStore(results)
    disc = store.read("discovery")
    named = disc[disc["kind"] == "named"]
    assert list(named["effect"]) == ["lever_arm"]
    assert " mm" in named["estimates"].iloc[0] and " ± " in named["estimates"].iloc[0]
    ev = store.read("discovery_evidence")
    ev = ev[ev["effect"] == "lever_arm"]
    assert len(ev) and set(ev["channel"]) <= {"ax", "ay", "az"}
    assert np.isfinite(ev[["x", "before", "fitted", "after"]].to_numpy(float)).all()
    # the effect explains the baseline residual: the residual after is much smaller
    assert ev["after"].abs().mean() < 0.5 * ev["before"].abs().mean()
    html = write_lot_report(results, "EV").read_text()
    assert 'class="evidence"' in html and "lever_arm · a" in html
