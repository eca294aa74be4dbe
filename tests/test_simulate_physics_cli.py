"""`mimucal simulate --physics`: a dataset from the independent physics simulator with a
catalogue effect hidden in its sensors, then `mimucal diagnose` on it as a user would."""

from __future__ import annotations

import json

import pytest

from flows.cli import main


def test_hidden_lever_arm_is_found_with_null_for_what_the_steps_cannot_see(tmp_path, capsys):
    data = tmp_path / "data"
    assert (
        main(
            [
                "simulate",
                str(data),
                "--physics",
                "--units",
                "1",
                "--reps",
                "3",
                "--hide",
                "lever_arm",
                "--no-tilted",
                "--seed",
                "3",
            ]
        )
        == 0
    )
    manifest = json.loads((data / "fleet.json").read_text())
    truth = manifest["units"][0]["hidden"][0]["params"]
    assert manifest["simulator"] == "physics" and manifest["tilted_steps"] is False
    out = tmp_path / "diag.json"
    assert main(["diagnose", str(data), "--unit", "U0001", "--json", str(out)]) == 0
    doc = json.loads(out.read_text())
    assert [e["name"] for e in doc["effects"]] == ["lever_arm"]
    est = doc["effects"][0]["estimate"]
    # the largest hidden component is found; what the steps cannot see is null, never NaN
    big = max(truth, key=lambda k: abs(truth[k]))
    assert est[big] == pytest.approx(truth[big], abs=0.5)
    assert any(v is None for v in est.values())
    assert "NaN" not in out.read_text()


def test_physics_options_are_checked(tmp_path, capsys):
    assert main(["simulate", str(tmp_path / "a"), "--physics", "--hide", "nope"]) == 2
    assert "unknown effect 'nope'" in capsys.readouterr().err
    assert main(["simulate", str(tmp_path / "b"), "--hide", "lever_arm"]) == 2
    assert "need --physics" in capsys.readouterr().err


def test_back_to_back_repetitions_show_an_accelerometer_scale_drift(tmp_path, capsys):
    """`--back-to-back`: the repetitions run on one warm-up, each at its own temperature, and
    diagnose names the accelerometer's scale drift the lack-of-fit tests take for noise."""
    import pandas as pd

    data = tmp_path / "data"
    args = ["simulate", str(data), "--physics", "--units", "1", "--reps", "5", "--seed", "4"]
    assert main(args + ["--hide", "thermal_scale_drift", "--back-to-back"]) == 0
    manifest = json.loads((data / "fleet.json").read_text())
    assert manifest["repetitions"] == "back to back on one warm-up"
    truth = manifest["units"][0]["hidden"][0]["params"]
    first = [
        float(pd.read_parquet(p, columns=["temp_c"])["temp_c"].iloc[0])
        for p in sorted(data.glob("lot=L01/unit=U0001/rep=*/samples.parquet"))
    ]
    assert len(first) == 5 and all(b > a + 0.2 for a, b in zip(first, first[1:]))
    out = tmp_path / "diag.json"
    assert main(["diagnose", str(data), "--unit", "U0001", "--json", str(out)]) == 0
    doc = json.loads(out.read_text())
    assert [e["name"] for e in doc["effects"]] == ["thermal_scale_drift"]
    big = max(truth, key=lambda k: abs(truth[k]))
    e = doc["effects"][0]
    assert abs(e["estimate"][big] - truth[big]) < 3 * e["stderr"][big]
    assert main(["simulate", str(tmp_path / "c"), "--back-to-back"]) == 2
    assert "need --physics" in capsys.readouterr().err
