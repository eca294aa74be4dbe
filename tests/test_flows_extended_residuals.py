"""A unit with a hidden effect: the nightly unit job keeps discovery's term, applies
discovery's joint calibration and stores the extended model's residuals beside the baseline."""

from __future__ import annotations

import numpy as np

from calib_core.effects import get_effect
from calib_core.sim.simulator import typical_truth
from flows.fleet_sim import simulate_fleet
from flows.nightly import UnitJob, calibrate_unit_job
from schemas.dataset import find_sessions


def test_hidden_nonlinearity_is_applied_and_its_residuals_stored(tmp_path):
    def truth_factory(rng, lot, unit):
        t = typical_truth(rng, gyro_noise_dps=0.05, gyro_bias_instability_dps=0.005)
        # z gyro cubic scale error: 0.3 deg/s at 1000 deg/s
        return t.with_effects((get_effect("gyro_scale_nonlinearity"), np.array([0, 0, 0, 0, 0, 0.3])))

    simulate_fleet(
        tmp_path / "data", lots=1, units=1, reps=3, seed=5, sample_rate_hz=20, truth_factory=truth_factory
    )
    refs, _ = find_sessions(tmp_path / "data")
    res = calibrate_unit_job(UnitJob("L01", "U0001", refs, "test"))
    names = [e["name"] for e in res.diagnosis["effects"]]
    assert names == ["gyro_scale_nonlinearity"], res.diagnosis
    applied = res.outcome.applied
    assert [t.name for t in applied.terms] == ["gyro_scale_nonlinearity"]
    assert abs(applied.terms[0].params[5] - 0.3) < 0.05
    models = set()
    for s in res.outcome.sessions:
        models |= set(s.residuals["model"])
    assert models == {"baseline", "extended"}
    # the extended model's z-gyro residual on fast multirate steps is far below the baseline's
    r = res.outcome.sessions[0].residuals
    fast = (r["channel"] == "gz") & (r["test"] == "multirate") & (r["rate_dps"].abs() >= 1000)
    rms = {
        m: float(np.sqrt((r[fast & (r["model"] == m)]["residual"] ** 2).mean()))
        for m in ("baseline", "extended")
    }
    assert rms["extended"] < rms["baseline"] / 3, rms
