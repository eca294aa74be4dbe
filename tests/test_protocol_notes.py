"""What a protocol cannot observe is said once per lot, not as every session's warning: on the
standard protocol without tilted steps (rotations about the body axes only), the lever-arm
components the dynamic steps cannot observe are a protocol note (P_LEVER_ARM_UNOBSERVED), the
sessions stay "ok", and the run's summary and the lot report say it once."""

from __future__ import annotations

import re

import numpy as np
import pandas as pd

from flows import runtime

runtime.ensure_environment()

from calib_core.sim import protocols  # noqa: E402
from flows.commands.nightly import print_outcome  # noqa: E402
from flows.fleet_sim import simulate_fleet  # noqa: E402
from flows.nightly import nightly_fleet_calibration  # noqa: E402
from schemas.protocol_notes import ProtocolNote, lot_notes, notes_of  # noqa: E402
from schemas.results_store import ResultsStore  # noqa: E402

RATE_HZ = 20.0


def test_notes_are_gathered_once_per_distinct_text():
    a = "P_LEVER_ARM_UNOBSERVED: these dynamic steps do not observe r1y: add tilted steps"
    b = "P_OTHER: something else"
    got = notes_of([("U1", [a]), ("U1", [a, a]), ("U2", np.array([a, b])), ("U3", None), ("U3", [])])
    assert got == [ProtocolNote("P_LEVER_ARM_UNOBSERVED", a, 3, 2), ProtocolNote("P_OTHER", b, 1, 1)]
    assert lot_notes(pd.DataFrame({"unit": ["U1"], "status": ["ok"]})) == []  # a store from before


def test_a_protocol_without_tilted_steps_warns_no_session_and_says_so_once(tmp_path, capsys):
    body_axes = protocols.dynamic_steps(tilted=False)
    steps = protocols.to_frame(protocols.xu2016_multirate() + protocols.xu2016_multiposition() + body_axes)
    data, results = tmp_path / "data", tmp_path / "results"
    simulate_fleet(data, 1, 3, 2, seed=11, sample_rate_hz=RATE_HZ, protocol=steps)
    log = nightly_fleet_calibration(data, results, run_discovery=False, progress=False)

    store = ResultsStore(results)
    sessions = store.read("sessions")
    assert len(sessions) == 6
    assert set(sessions["status"]) == {"ok"}, sessions[["unit", "rep", "status", "warnings"]]
    assert not any(len(w) for w in sessions["warnings"])
    # the note names exactly the components stored as NaN (not observed), on every session
    params = store.read("parameters")
    arms = params[params["model"] == "lever_arm"]
    nan_names = sorted(set(arms.loc[arms["value"].isna(), "parameter"]))
    assert nan_names, "the body-axis-only dynamic steps leave some lever-arm component unobserved"
    notes = lot_notes(sessions)
    assert len(notes) == 1 and notes[0].code == "P_LEVER_ARM_UNOBSERVED"
    assert (notes[0].sessions, notes[0].units) == (6, 3)
    named = re.search(r"do not observe (.*): add tilted steps", notes[0].text).group(1).split(", ")
    assert sorted(named) == nan_names

    # the run's summary: once for the lot
    assert [(n["lot"], n["sessions"], n["units"]) for n in log["protocol_notes"]] == [("L01", 6, 3)]
    print_outcome(log)
    out = capsys.readouterr().out
    assert out.count("P_LEVER_ARM_UNOBSERVED") == 1, out
    assert "protocol of lot L01: P_LEVER_ARM_UNOBSERVED" in out

    # the lot report: sessions ok 6, warned 0, and the note once in its summary
    html = (results / "reports" / "L01.html").read_text()
    summary = html[html.index('<section id="summary">') : html.index('<section id="parameters">')]
    assert re.search(r'Sessions ok</div><div class="v">6<', summary), summary[:2000]
    assert re.search(r'Warned</div><div class="v">0<', summary), summary[:2000]
    assert summary.count("P_LEVER_ARM_UNOBSERVED") == 1
    assert html.count("P_LEVER_ARM_UNOBSERVED") == 1
