"""Model discovery on the estimator's own simulator (:mod:`calib_core.sim.simulator`), where a test
needs the exact model: standard errors against the Monte Carlo spread, the diagnosis
document, the repetitions it needs. Hidden effects, clean lots and effects outside the
catalogue are tested on the independent physics simulator (test_discovery_physics.py)."""

from __future__ import annotations

import json

import numpy as np
import pytest

from calib_core.discovery import diagnose_unit
from calib_core.effects import get_effect
from calib_core.errors import DesignError
from calib_core.sim import protocols
from calib_core.sim import simulator as sim
from calib_core.sim.simulator import REALISTIC_NOISE, simulate_unit

STEPS = protocols.default_session()
N_REPS = 5


def base_truth(rng):
    # a warm-up temperature curve is recorded in every lot, clean or not, so that the
    # thermal term is always a candidate
    return sim.typical_truth(rng, **REALISTIC_NOISE, temperature=sim.TemperatureProfile())


@pytest.mark.slow
def test_stderr_matches_monte_carlo_spread():
    """Same unit, 40 independent lots of repetitions: the spread of the estimate of the
    asymmetry on z agrees with its reported standard error (within 25 %)."""
    rng = np.random.default_rng(77)
    truth = base_truth(rng).with_effects((get_effect("gyro_scale_asymmetry"), [0, 0, 400.0]))
    est, se = [], []
    for _ in range(40):
        sessions, _ = simulate_unit(truth, STEPS, rng, N_REPS)
        d = diagnose_unit(sessions, tables=False)
        assert [e.name for e in d.effects] == ["gyro_scale_asymmetry"]
        est.append(d.effects[0].estimate["a_z"])
        se.append(d.effects[0].stderr["a_z"])
    est, se = np.array(est), np.array(se)
    assert abs(est.mean() - 400.0) < 3 * est.std(ddof=1) / np.sqrt(len(est))
    assert 0.75 < est.std(ddof=1) / se.mean() < 1.25, (est.std(ddof=1), se.mean())


def test_diagnosis_document_and_terms():
    rng = np.random.default_rng(5)
    truth = base_truth(rng).with_effects((get_effect("gyro_g_sensitivity"), [0, 0, 0, 0, 0, 0, 0.04, 0, 0]))
    sessions, _ = simulate_unit(truth, STEPS, rng, 3, lot="L9", unit="U9")
    d = diagnose_unit(sessions)
    doc = json.loads(json.dumps(d.to_dict(), allow_nan=False))
    assert doc["unit"] == "U9" and doc["misfit"] is True and doc["unexplained"] is False
    (eff,) = doc["effects"]
    assert eff["name"] == "gyro_g_sensitivity" and eff["axes"] == ["z"]
    assert set(eff) >= {
        "name",
        "axes",
        "estimate",
        "stderr",
        "evidence",
        "heldout_rms_before",
        "heldout_rms_after",
        "gain",
    }
    assert eff["gain"] == pytest.approx(eff["heldout_rms_before"] / eff["heldout_rms_after"])
    assert abs(eff["estimate"]["Gzx"] - 0.04) < 4 * eff["stderr"]["Gzx"]
    (tv,) = d.terms
    assert tv.name == "gyro_g_sensitivity" and tv.params[6] == pytest.approx(0.04, abs=0.005)
    # residual tables: before, gz misfits during multiposition; after, it does not
    rms = {}
    for which, table in (("before", d.residuals_before), ("after", d.residuals_after)):
        sub = table[(table.channel == "gz") & (table.test == "multiposition")]
        rms[which] = float(np.sqrt(np.mean((sub.residual / sub.sigma) ** 2)))
    assert rms["before"] > 2.0 and rms["after"] < 1.3, rms
    # the extended calibration removes the error it found: applied to the step means it
    # leaves gz within noise on the multiposition steps
    cal = d.calibrations_after[0]
    sm = sessions[0].of_test("multiposition")
    w, _ = cal.apply(sm.gyro, sm.accel, temp_c=sm.temp_c, t=sm.t_mid)
    assert np.sqrt(np.mean((w[:, 2] - sm.w_ref[:, 2]) ** 2)) < 0.03


def test_needs_two_repetitions():
    rng = np.random.default_rng(6)
    sessions, _ = simulate_unit(base_truth(rng), STEPS, rng, 1)
    with pytest.raises(DesignError) as err:
        diagnose_unit(sessions)
    assert err.value.code == "E_DISCOVERY_REPS"
