"""Effects that differ between the repetitions (the five repetitions run back to back on
one warm-up, so each sits at its own temperature): the physics simulator's power-on clock,
and the between-repetition test of "the unit misfits" that sees what the lack-of-fit tests
take for noise (docs/model-discovery.md, "Repetitions at different temperatures")."""

from __future__ import annotations

import numpy as np
import pytest

from calib_core.discovery import diagnose_unit
from calib_core.discovery.turntable import _Discovery
from calib_core.effects import get_effect
from calib_core.sim import protocols
from calib_core.sim.physics import Turntable, WarmUp, typical_physics_unit
from schemas.physics_sessions import _sessions, physics_unit_step_means
from tools.discovery_evaluation_ident import sensor_effect_scenario


def back_to_back(unit, steps, rng, unit_id, table=None):
    return physics_unit_step_means(
        unit, steps, rng, n_reps=5, unit_id=unit_id, table=table or Turntable(), back_to_back=True
    )


def cold_starts(unit, steps, rng, unit_id, table=None):
    return physics_unit_step_means(unit, steps, rng, n_reps=5, unit_id=unit_id, table=table or Turntable())


def _short_steps():
    return protocols.default_session(dynamic=False)


def test_back_to_back_repetitions_continue_one_warm_up_and_one_bias_trend():
    """Each repetition starts where the last left the sensor (a minute later): the recorded
    temperature and the bias trend run on the power-on clock, not the session's."""
    rng = np.random.default_rng(5)
    warm = WarmUp(start_c=20.0, rise_c=12.0, tau_s=500.0, noise_c=0.0)
    unit = typical_physics_unit(rng, temperature=warm)
    quiet = dict(white_density=0.0, instability=0.0, turn_on=0.0, random_walk=0.0)
    unit = unit.replace_gyro(0, bias_per_h=3.6, **quiet)  # 0.001 deg/s per second
    steps = _short_steps()
    reps = list(_sessions(unit, steps, rng, 3, 50.0, Turntable(), True, 60.0))
    power_on = 0.0
    for _rep, samples, _md in reps:
        t = samples["t"].to_numpy(float)
        expected = warm.at(t + power_on)
        assert np.allclose(samples["temp_c"].to_numpy(float), expected, atol=1e-4)
        still = (samples["step"] == 0).to_numpy()
        # gyro x: its bias trend counts from power-on (the first step is stationary)
        gx = samples["gx"].to_numpy(float)[still] / unit.gyros[0].scale
        trend = 3.6 * (t[still] + power_on) / 3600.0
        assert np.allclose(gx - trend, (gx - trend).mean(), atol=1e-4)
        power_on += t[-1] + 1.0 / 50.0 + 60.0
    starts = [md["session_start"] for _, _, md in reps]
    assert starts == sorted(starts) and len(set(starts)) == 3
    # cold starts: every repetition from the same temperature, or from a day's ambient
    cold = list(_sessions(unit, steps, rng, 2, 50.0, Turntable(), False, 60.0))
    assert cold[0][1]["temp_c"].iloc[0] == pytest.approx(cold[1][1]["temp_c"].iloc[0], abs=1e-4)
    days = list(_sessions(unit, steps, rng, 4, 50.0, Turntable(), False, 60.0, ambient_sd_c=2.0))
    starts_c = [float(s["temp_c"].iloc[0]) for _, s, _ in days]
    assert np.std(starts_c) > 0.3 and all(15.0 < c < 25.0 for c in starts_c)
    for _, s, _ in days:  # each day's warm-up still rises 12 degC from its own start
        t = s["t"].to_numpy(float)
        assert s["temp_c"].iloc[-1] - s["temp_c"].iloc[0] == pytest.approx(
            12.0 * (1 - np.exp(-t[-1] / 500.0)), abs=1e-3
        )


def test_between_repetition_test_runs_only_where_a_column_differs_between_repetitions():
    rng = np.random.default_rng(11)
    unit = typical_physics_unit(rng)
    steps = protocols.default_session()
    d_cold = _Discovery(cold_starts(unit, steps, rng, "C"), 0.01)
    assert all(d_cold.between_repetition_test(g, 0.01) is None for g in d_cold.test_groups())
    d_b2b = _Discovery(back_to_back(unit, steps, rng, "B"), 0.01)
    ran = {"+".join(g) for g in d_b2b.test_groups() if d_b2b.between_repetition_test(g, 0.01) is not None}
    # only the temperature-driven terms: time since the session started is the same in each
    assert ran == {"thermal_bias_drift", "thermal_scale_drift"}


@pytest.mark.slow
def test_between_repetition_p_values_of_clean_units_are_calibrated():
    """On 40 clean units run back to back, the thermal terms' between-repetition p-values
    below 0.1 stay within three binomial standard deviations of 10 % (500 units measured:
    docs/model-discovery.md)."""
    rng = np.random.default_rng(2026)
    steps = protocols.default_session()
    p = []
    for u in range(40):
        d = _Discovery(back_to_back(typical_physics_unit(rng), steps, rng, f"C{u}"), 0.01)
        for name in ("thermal_bias_drift", "thermal_scale_drift"):
            p.append(d.between_repetition_test((name,), 1.0).p_value)
    p = np.asarray(p)
    n = len(p)
    assert abs(np.sum(p <= 0.1) - 0.1 * n) <= 3 * np.sqrt(n * 0.1 * 0.9), np.sort(p)[:12]
    assert np.sum(p <= 0.01) <= 3, np.sort(p)[:6]


@pytest.mark.slow
def test_an_accelerometer_scale_drift_between_repetitions_is_named_on_its_sensor():
    """An accelerometer's scale drift at 200 ppm/degC: with cold starts the repetitions share
    one temperature history and the unit does not misfit; back to back, the repetitions'
    temperatures differ by up to 7 degC and the between-repetition test sees the scale move."""
    term = get_effect("thermal_scale_drift")
    steps = protocols.default_session()
    from flows.commands.diagnose import summary_lines

    named, texts = 0, []
    for k, sensor in enumerate((3, 4, 5, 3, 4, 5)):
        rng = np.random.default_rng(300 + k)
        theta = np.zeros(6)
        theta[sensor] = 200.0 if k % 2 else -200.0
        unit = typical_physics_unit(rng)
        for (kind, i), changes in term.physics_knobs(theta).items():
            unit = getattr(unit, f"replace_{kind}")(i, **changes)
        d = diagnose_unit(back_to_back(unit, steps, rng, f"A{k}"), tables=False)
        texts += summary_lines(d)
        assert "thermal_scale_drift" in d.misfit_between, d.to_dict()["misfit_terms"]
        if [e.name for e in d.effects] == ["thermal_scale_drift"]:
            e = d.effects[0]
            right = term.param_names[sensor]
            named += abs(e.estimate[right] - theta[sensor]) < 3 * e.stderr[right]
    assert named >= 5
    # where no lack-of-fit test rejects, the text says which test found the misfit
    verdict = "MISFIT (between-repetition test of thermal_scale_drift; no lack-of-fit test rejects)"
    assert any(verdict in line for line in texts)


@pytest.mark.slow
def test_back_to_back_repetitions_tell_time_drift_from_temperature():
    """Cold starts give every repetition the same ramp, so a bias trend in time is confounded
    with temperature; back to back, the repetitions' temperature slopes differ and time is
    named alone."""
    o = sensor_effect_scenario(back_to_back, protocols.default_session(), "bias_time_drift", 6, seed=28)
    assert o.named_alone >= 5 and o.other_named == 0, o.notes


def test_step_consistency_check_takes_out_a_scale_temperature_coefficient_shared_by_the_repetitions():
    """Back to back, a gyro of 254 ppm/degC has its fast steps differ between repetitions by
    up to 7 deg/s, moving within each repetition too: none is taken for damage (before the
    shared coefficient was taken out, fast steps of several repetitions were), while a step
    damaged by 1 deg/s in one repetition still is."""
    from dataclasses import replace as dc_replace

    from calib_core.guards import inconsistent_steps

    rng = np.random.default_rng(9)
    unit = typical_physics_unit(rng).replace_gyro(2, scale_tc_ppm=254.0)
    sms = back_to_back(unit, protocols.default_session(), rng, "T")
    assert inconsistent_steps(sms) == []
    i = int(np.flatnonzero(sms[1].rate_dps == 1000.0)[0])
    gyro = sms[1].gyro.copy()
    gyro[i, 2] += 1.0
    sms[1] = dc_replace(sms[1], gyro=gyro)
    found = inconsistent_steps(sms)
    assert [(f.index, f.step, f.channel) for f in found] == [(1, int(sms[1].step[i]), "gz")]
