"""`mimucal nightly` on a lot where every unit has a lever arm and the protocol has no tilted
dynamic steps: the flow succeeds, discovery names the lever arm, and the calibration files
carry its determined components and ``null`` for the ones the steps cannot determine."""

from __future__ import annotations

import json

import numpy as np
import pytest

from flows import runtime

runtime.ensure_environment()

from calib_core.effects import get_effect  # noqa: E402
from calib_core.sim import protocols  # noqa: E402
from calib_core.sim.physics import typical_physics_unit  # noqa: E402
from flows.cli import main as cli_main  # noqa: E402
from schemas.physics_sessions import write_physics_unit  # noqa: E402


@pytest.mark.slow
def test_nightly_with_lever_arms_and_no_tilted_steps(tmp_path, capsys):
    data, results = tmp_path / "data", tmp_path / "results"
    rng = np.random.default_rng(2117)
    steps = protocols.default_session(dynamic=False)
    for u in range(2):
        unit, _, _ = get_effect("lever_arm").hide(typical_physics_unit(rng), rng)
        write_physics_unit(data, unit, steps, rng, n_reps=3, rate_hz=20.0, lot="LV", unit_id=f"U{u}")
    assert cli_main(["nightly", str(data), "--results", str(results)]) == 0
    files = sorted(results.rglob("*.json"))
    cals = [json.loads(p.read_text()) for p in files if '"terms"' in p.read_text()]
    assert len(cals) == 2, [str(p) for p in files]
    for cal in cals:
        (lever,) = [t for t in cal["terms"] if t["name"] == "lever_arm"]
        determined = [v for v in lever["params"].values() if v is not None]
        assert determined and all(np.isfinite(determined))
        for p in lever.get("undetermined", {}):
            assert lever["params"][p] is None and lever["stderr"][p] is None
