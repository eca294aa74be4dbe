"""Temperature against time, and the thermal scale drift, on the independent physics
simulator (small seeded samples of the figures in docs/model-discovery.md, "Earth rate and
thermal terms"): near-collinear terms decided by the data, the advice that separates them,
the scale drift named on the right sensor."""

from __future__ import annotations

import numpy as np
import pytest

from calib_core.discovery import diagnose_unit
from calib_core.discovery.identifiability import analyse, near_confounded
from calib_core.discovery.plan import (
    TEMPERATURE_CHANGES,
    _curved_warm_up,
    _with_temperature,
    advise,
    design,
    plan,
)
from calib_core.effects import get_effect
from calib_core.sim import protocols
from calib_core.sim.physics import Turntable, WarmUp, typical_physics_unit
from flows.commands.diagnose import summary_lines
from schemas.physics_sessions import physics_unit_step_means
from tools.discovery_evaluation_ident import sensor_effect_scenario

CURVED = WarmUp(rise_c=10.0, tau_s=150.0)
WARM_UP_LABEL, SOAK_LABEL, BACK_TO_BACK_LABEL = TEMPERATURE_CHANGES


def step_means_of(unit, steps, rng, unit_id, table=None):
    return physics_unit_step_means(unit, steps, rng, n_reps=5, unit_id=unit_id, table=table or Turntable())


def test_near_confounded_pairs_are_those_between_the_two_thresholds():
    rng = np.random.default_rng(0)
    x, y, z, w = np.linalg.qr(rng.normal(size=(50, 4)))[0].T
    terms = {
        "a": x[:, None],
        "b": (x + 0.1 * y)[:, None],  # sine 0.0995 with a
        "c": (x + 0.01 * z)[:, None],  # sine 0.01 with a: confounded, not near
        "d": np.column_stack([w, x + 0.5 * y]),  # own direction w; its best angle with a: 0.447
    }
    pairs = {c.terms: c.sin_angle for c in near_confounded(terms)}
    assert set(pairs) == {("a", "b"), ("b", "c")}
    assert pairs[("a", "b")] == pytest.approx(0.1 / np.sqrt(1.01), rel=1e-9)
    # the same pair below the first threshold is analyse's business, not this one's
    assert {
        c.terms for c in analyse(np.zeros((50, 0)), {"a": terms["a"], "c": terms["c"]}, {}).confounded
    } == {("a", "c")}


@pytest.mark.slow
def test_plan_says_a_curved_warm_up_or_a_soak_separates_temperature_from_time():
    steps = protocols.default_session()
    advice = {a.terms: a.separated_by for a in advise(steps)}
    sep = advice[("bias_time_drift", "thermal_bias_drift")]
    assert WARM_UP_LABEL in sep and SOAK_LABEL in sep and BACK_TO_BACK_LABEL in sep
    # the curved warm-up really separates them on the plan's own design
    base, terms, pnames = design(_curved_warm_up(steps))
    ident = analyse(base, terms, pnames)
    assert not any("thermal_bias_drift" in c.terms for c in ident.confounded)
    # a soak is no new motion: it does not separate the Earth rate from g-sensitivity
    whole = {a.terms: a.separated_by for a in advise(protocols.whole_turn_session())}
    assert SOAK_LABEL not in whole[("earth_rate", "gyro_g_sensitivity")]


@pytest.mark.slow
def test_plan_lists_a_near_collinear_pair_and_what_separates_it():
    # a 400 s warm-up: temperature and time at a sine of about 0.1 on the nominal design
    p = plan(_with_temperature(protocols.default_session(), 400.0))
    near = {c.terms: c.sin_angle for c in p.near}
    assert 0.05 <= near[("bias_time_drift", "thermal_bias_drift")] < 0.15
    assert not any("thermal_bias_drift" in c.terms for c in p.identifiability.confounded)
    advice = {a.issue.split(" (")[0]: a.separated_by for a in p.advice}
    sep = advice["near-confounded: bias_time_drift, thermal_bias_drift"]
    assert WARM_UP_LABEL in sep and SOAK_LABEL in sep
    assert any(ln.startswith("  near-confounded: bias_time_drift, thermal_bias_drift") for ln in p.lines())


@pytest.mark.slow
def test_thermal_drift_on_a_warm_up_linear_in_time_is_confounded_never_time_alone():
    o = sensor_effect_scenario(step_means_of, protocols.default_session(), "thermal_bias_drift", 6, seed=22)
    assert o.other_named == 0, o.notes  # bias_time_drift never named for it
    assert o.confounded + o.named >= 4, o.notes


@pytest.mark.slow
def test_confounded_thermal_diagnosis_applies_both_and_says_what_separates_them():
    rng = np.random.default_rng(22)
    unit, _, what = get_effect("thermal_bias_drift").hide(typical_physics_unit(rng), rng)
    d = diagnose_unit(step_means_of(unit, protocols.default_session(), rng, "U"), tables=False)
    assert [c.terms for c in d.confounded] == [("bias_time_drift", "thermal_bias_drift")]
    assert d.effects == []
    c = d.confounded[0]
    # no channel's lack-of-fit test rejects on this unit (its targeted test does): the pair is
    # judged on the sensor its joint parameters act on, not diluted over all six channels
    # (where its held-out gain is 1.05, below the line; named on 0 before the joint test)
    assert what.endswith("az") and c.channels == ("az",) and c.gain >= 1.3, (what, c.channels, c.gain)
    assert 0.05 <= c.sin_angle < 0.15 and not c.separable
    assert {t.name for t in d.terms} == {"bias_time_drift", "thermal_bias_drift"}  # combined fit
    text = "\n".join(summary_lines(d))
    assert "confounded: [bias_time_drift, thermal_bias_drift] (combined fit applied; none named)" in text
    assert "a warm-up that is not linear in time" in text


@pytest.mark.slow
def test_a_curved_warm_up_tells_temperature_from_time():
    steps = protocols.default_session()
    o = sensor_effect_scenario(step_means_of, steps, "thermal_bias_drift", 6, seed=24, warm_up=CURVED)
    assert o.named_alone >= 5 and o.other_named == 0, o.notes
    o = sensor_effect_scenario(step_means_of, steps, "bias_time_drift", 6, seed=25, warm_up=CURVED)
    assert o.named_alone >= 4 and o.other_named == 0, o.notes


@pytest.mark.slow
def test_clean_units_name_nothing_and_report_no_confounded_group():
    rng = np.random.default_rng(77)
    for u in range(8):
        d = diagnose_unit(
            step_means_of(typical_physics_unit(rng), protocols.default_session(), rng, f"C{u}"), tables=False
        )
        assert not d.effects and not d.confounded, (u, d.confounded_set_aside)


@pytest.mark.slow
@pytest.mark.parametrize(("sensor", "ppm"), [(0, 60.0), (1, -60.0), (2, 60.0), (4, 300.0)])
def test_thermal_scale_drift_named_on_its_sensor(sensor, ppm):
    """On the default protocol a gyro's coefficient has a standard error of 1.5-2.5
    ppm/degC, but at 30 ppm/degC its held-out gain straddles min_gain (1.03-1.07); an
    accelerometer's standard error is 10-17 ppm/degC (docs/model-discovery.md)."""
    term = get_effect("thermal_scale_drift")
    rng = np.random.default_rng(100 + sensor)
    theta = np.zeros(6)
    theta[sensor] = ppm
    unit = typical_physics_unit(rng)
    for (kind, i), changes in term.physics_knobs(theta).items():
        unit = getattr(unit, f"replace_{kind}")(i, **changes)
    d = diagnose_unit(step_means_of(unit, protocols.default_session(), rng, "S"), tables=False)
    assert [e.name for e in d.effects] == ["thermal_scale_drift"], d.to_dict()
    e = d.effects[0]
    t = {k: abs(v) / e.stderr[k] for k, v in e.estimate.items()}
    right = term.param_names[sensor]
    assert max(t, key=t.get) == right
    assert abs(e.estimate[right] - ppm) < 3 * e.stderr[right]


@pytest.mark.slow
def test_a_thermal_drift_on_the_gyro_the_nonlinearity_already_fixes_is_still_found():
    """Two effects on one gyro: its channel misfits at baseline, and the nonlinearity alone
    already fixes that, so the thermal drift fixes no channel. It is then judged by its own
    targeted test, as when no channel misfits. Measured on these 6 units: found (in the
    confounded pair with time) beside the named nonlinearity on 6, before that rule on 4."""
    rng = np.random.default_rng(77)
    found = 0
    for u in range(6):
        unit, theta, _ = get_effect("gyro_scale_nonlinearity").hide(typical_physics_unit(rng), rng)
        gyro = int(np.flatnonzero(theta[:3])[0])
        drift = np.zeros(6)  # 0.005-0.02 deg/s/degC, the realistic size, on the same gyro
        drift[gyro] = (1.0 if rng.random() < 0.5 else -1.0) * rng.uniform(0.005, 0.02)
        for (kind, i), knobs in get_effect("thermal_bias_drift").physics_knobs(drift).items():
            unit = getattr(unit, f"replace_{kind}")(i, **knobs)
        d = diagnose_unit(step_means_of(unit, protocols.default_session(), rng, f"S{u}"), tables=False)
        named = {e.name for e in d.effects}
        thermal = "thermal_bias_drift" in named or any("thermal_bias_drift" in c.terms for c in d.confounded)
        assert named <= {"gyro_scale_nonlinearity", "thermal_bias_drift"}, named
        found += "gyro_scale_nonlinearity" in named and thermal
    assert found >= 5, found
