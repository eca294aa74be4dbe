"""From files to E_UNDETERMINED: a protocol without rotation about one axis, and saturation
that leaves too little, read fine but cannot determine K_g; the session error names the
session and what is undetermined. (Uses the xu2016 estimator as the pipeline does.)"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from calib_core.errors import DesignError
from calib_core.models.xu2016 import fit_gyro_multirate
from calib_core.sim import protocols
from calib_core.sim import simulator as sim
from calib_core.steps import SessionKey
from schemas.averaging import read_step_means
from schemas.dataset import SessionRef
from schemas.errors import E_UNDETERMINED, W_SATURATED, from_design_error
from schemas.writer import write_session

RATE = 20.0
KEY = SessionKey("L1", "U001", 4)


def _fit_or_session_error(ref):
    sm, warnings = read_step_means(ref)
    try:
        fit_gyro_multirate(sm)
    except DesignError as exc:
        return from_design_error(exc, str(ref.key), "steps.parquet"), warnings
    return None, warnings


def test_no_rotation_about_x_is_undetermined(tmp_path):
    rng = np.random.default_rng(1)
    truth = sim.typical_truth(rng)
    steps = protocols.default_session(duration_s=1.0, settle_s=0.2, dynamic=False)
    steps = steps[~((steps["test"] == "multirate") & (steps["up_axis"] == "+x"))]
    samples = sim.simulate_session(truth, steps, rng, RATE)
    ref = SessionRef(KEY, write_session(tmp_path, KEY, steps, samples, sim.session_metadata(truth, RATE)))
    err, warnings = _fit_or_session_error(ref)
    assert warnings == []
    assert err is not None and err.code == E_UNDETERMINED
    msg = str(err)
    assert str(KEY) in msg and "steps.parquet" in msg and "axis x" in msg
    print(msg)


def test_saturation_that_removes_an_axis_is_undetermined(tmp_path, monkeypatch):
    """x gyro rated +/-5 deg/s: every x-up multirate step saturates and is left out (named),
    and then the design cannot determine K_g. (18 of 94 steps lost is more than the 5 % a
    session may lose, E_TOO_MANY_STEPS_LOST, checked first; the share is lifted here to reach
    the design check.)"""
    monkeypatch.setenv("MIMUCAL_MAX_LOST_STEP_SHARE", "1")
    rng = np.random.default_rng(2)
    truth = replace(sim.typical_truth(rng, misalignment=0.0), gyro_range_dps=(5.0, 350.0, 4000.0))
    steps = protocols.default_session(duration_s=1.0, settle_s=0.2, dynamic=False)
    samples = sim.simulate_session(truth, steps, rng, RATE)
    ref = SessionRef(KEY, write_session(tmp_path, KEY, steps, samples, sim.session_metadata(truth, RATE)))
    err, warnings = _fit_or_session_error(ref)
    x_rates = steps[(steps["test"] == "multirate") & (steps["up_axis"] == "+x")]["step"]
    assert set(x_rates) <= {w.step for w in warnings if w.code == W_SATURATED}
    assert err is not None and err.code == E_UNDETERMINED and str(KEY) in str(err)


@pytest.mark.parametrize("drop", ["+y", "+z"])
def test_full_protocol_minus_one_axis(tmp_path, drop):
    rng = np.random.default_rng(3)
    truth = sim.typical_truth(rng)
    steps = protocols.default_session(duration_s=1.0, settle_s=0.2, dynamic=False)
    steps = steps[~((steps["test"] == "multirate") & (steps["up_axis"] == drop))]
    samples = sim.simulate_session(truth, steps, rng, RATE)
    ref = SessionRef(KEY, write_session(tmp_path, KEY, steps, samples, sim.session_metadata(truth, RATE)))
    err, _ = _fit_or_session_error(ref)
    assert err is not None and err.code == E_UNDETERMINED
    assert f"axis {drop[1]}" in str(err)
