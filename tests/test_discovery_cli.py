"""`mimucal diagnose` end to end on a small simulated dataset written to Parquet."""

from __future__ import annotations

import json

import numpy as np
import pandas as pd

from calib_core.effects import get_effect
from calib_core.sim import protocols
from calib_core.sim import simulator as sim
from calib_core.sim.simulator import REALISTIC_NOISE
from calib_core.steps import SessionKey
from flows.cli import main
from schemas.writer import write_session

RATE = 50.0


def write_unit(root, truth, n_reps, rng, unit="U7"):
    steps = protocols.default_session(duration_s=1.0, settle_s=0.2)
    for r in range(1, n_reps + 1):
        tr = sim.draw_repetition_truth(truth, rng)
        samples = sim.simulate_session(tr, steps, rng, sample_rate_hz=RATE)
        write_session(root, SessionKey("L1", unit, r), steps, samples, sim.session_metadata(tr, RATE))


def test_diagnose_names_the_effect_and_writes_json(tmp_path, capsys):
    rng = np.random.default_rng(11)
    truth = sim.typical_truth(rng, **REALISTIC_NOISE).with_effects(
        (get_effect("gyro_scale_asymmetry"), [0.0, 0.0, 800.0])
    )
    write_unit(tmp_path / "ds", truth, 3, rng)
    out = tmp_path / "diag.json"
    res = tmp_path / "res.parquet"
    rc = main(["diagnose", str(tmp_path / "ds"), "--unit", "U7", "--json", str(out), "--residuals", str(res)])
    assert rc == 0
    text = capsys.readouterr().out
    assert "gyro_scale_asymmetry on z" in text and "MISFIT on gz" in text
    doc = json.loads(out.read_text())
    assert doc["unit"] == "U7" and doc["misfit"] and not doc["unexplained"]
    (eff,) = doc["effects"]
    assert eff["name"] == "gyro_scale_asymmetry" and eff["axes"] == ["z"]
    assert abs(eff["estimate"]["a_z"] - 800.0) < 5 * eff["stderr"]["a_z"]
    assert eff["gain"] > 3
    table = pd.read_parquet(res)
    assert set(table["model"]) == {"affine", "extended", "xu2016"}
    assert "xu2016 calibration replayed" in text
    assert {"lot", "unit", "rep", "step", "test", "channel", "reference", "residual", "sigma"} <= set(
        table.columns
    )
    assert len(table) == 3 * 3 * 6 * 118


def test_diagnose_refuses_a_single_repetition(tmp_path, capsys):
    rng = np.random.default_rng(12)
    write_unit(tmp_path / "ds", sim.typical_truth(rng, **REALISTIC_NOISE), 1, rng)
    rc = main(["diagnose", str(tmp_path / "ds"), "--unit", "U7"])
    assert rc == 2
    assert "at least 2" in capsys.readouterr().err


def test_diagnose_unknown_unit(tmp_path, capsys):
    (tmp_path / "ds").mkdir()
    assert main(["diagnose", str(tmp_path / "ds"), "--unit", "NOPE"]) == 2
    assert "no session" in capsys.readouterr().err
