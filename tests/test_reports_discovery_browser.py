"""The discovery section of a lot report in Debian's headless Chromium, on real diagnoses of
physics-simulated units, one per finding kind: a named effect (thermal scale drift), a
confounded pair (Earth rate and g-sensitivity on whole turns about the vertical), a misfit
no catalogue effect explains (a periodic rate error), a negligible term (the Earth rate seen
by a typical MEMS gyro). Checks that each finding's evidence figures are drawn, that no table
cell holds JSON, and takes the screenshots of the section and of one unit's evidence (in the
test's temporary directory; into docs/img/, which the docs show, with
``MIMUCAL_SCREENSHOTS=docs``: the suite leaves the repository's files as they are)."""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from calib_core.discovery import diagnose_unit
from calib_core.discovery.presentation import finding_rows
from calib_core.effects import get_effect
from calib_core.sim import protocols
from calib_core.sim.physics import Turntable, typical_physics_unit
from reports.browser import Chromium, find_chromium
from reports.lot import write_lot_report
from schemas.physics_sessions import physics_unit_step_means
from schemas.results_store import ResultsStore
from tools.discovery_evaluation import OUT_OF_CATALOGUE
from tools.discovery_evaluation_ident import quiet_gyros
from tools.synthetic_store import build_synthetic_store

pytestmark = [
    pytest.mark.browser,
    pytest.mark.slow,
    pytest.mark.skipif(
        find_chromium() is None, reason="Debian's chromium is not installed (run tools/install-browser.sh)"
    ),
]
DOCS_IMG = Path(__file__).resolve().parent.parent / "docs" / "img"


def _diagnosis(kind: str):
    rng = np.random.default_rng(1)
    unit, table, steps, reps = typical_physics_unit(rng), Turntable(), protocols.default_session(), 3
    if kind == "named":
        unit, _, _ = get_effect("thermal_scale_drift").hide(unit, rng, 1.0)
    elif kind == "confounded":
        unit, table, steps, reps = (
            quiet_gyros(unit),
            Turntable(latitude_deg=45.0),
            protocols.whole_turn_session(),
            5,
        )
    elif kind == "unexplained":
        unit, _ = OUT_OF_CATALOGUE["periodic_rate_error"](unit, rng, 1.0)
    else:  # negligible: the Earth rate below a typical MEMS gyro's noise
        table = Turntable(latitude_deg=45.0)
    return diagnose_unit(physics_unit_step_means(unit, steps, rng, n_reps=reps, table=table), tables=False)


@pytest.fixture(scope="module")
def report(tmp_path_factory):
    root = tmp_path_factory.mktemp("discovery-browser")
    truth = build_synthetic_store(
        root, n_units=4, n_outliers=0, n_failed=0, seed=3, discovery=False, navigation=False
    )
    rows, evidence = [], []
    for unit, kind in zip(truth.units, ("named", "confounded", "unexplained", "negligible")):
        d = _diagnosis(kind)
        rows += [{**r, "lot": truth.lot, "unit": unit} for r in finding_rows(d)]
        if len(d.evidence):
            evidence.append(d.evidence.assign(lot=truth.lot, unit=unit))
    rows = pd.DataFrame(rows)
    store = ResultsStore(root)
    store.write("discovery", rows)
    store.write("discovery_evidence", pd.concat(evidence, ignore_index=True))
    return truth, rows, write_lot_report(root, truth.lot)


@pytest.fixture(scope="module")
def page(report, tmp_path_factory):
    truth, rows, path = report
    shots = DOCS_IMG if os.environ.get("MIMUCAL_SCREENSHOTS") == "docs" else tmp_path_factory.mktemp("shots")
    with Chromium(width=1400, height=1000, timeout_s=120) as b:
        b.open(path)
        b.wait_figures()
        b.evaluate("mimucalExpandAll(true)")
        b.wait_figures()
        b.pump(0.3)
        facts = b.evaluate("""(function(){
            var cells = Array.from(document.querySelectorAll('#discovery td, #units td'));
            var ev = Array.from(document.querySelectorAll('.evidence .figure'));
            return {
              cells: cells.map(function(c){return c.textContent;}),
              evidence: ev.length,
              evidenceDrawn: ev.filter(function(f){
                  return f.getAttribute('data-state') === 'rendered' &&
                         f.querySelectorAll('.scatterlayer .trace').length >= 2;}).length,
              titles: Array.from(document.querySelectorAll('.evidence h5')).map(
                  function(h){return h.textContent;}),
              negligible: Array.from(document.querySelectorAll('details.negligible li')).map(
                  function(l){return l.textContent;})};
        })()""")
        if os.environ.get("MIMUCAL_SCREENSHOTS", "1") != "0":
            b.evaluate(
                "document.querySelectorAll('details.unit').forEach(function(d){"
                f"d.open = d.getAttribute('data-unit') === {json.dumps(truth.units[1])};}});"
                "document.getElementById('discovery').scrollIntoView();"
            )
            b.screenshot(shots / "discovery-section.png", clip_selector="#discovery", max_height=1400)
            sel = f'details.unit[data-unit="{truth.units[1]}"] .evidence'
            b.evaluate(f"document.querySelector({json.dumps(sel)}).scrollIntoView();")
            b.pump(0.3)
            b.screenshot(shots / "discovery-evidence.png", clip_selector=sel, max_height=1400)
        yield facts, b.log.errors


def test_one_unit_per_finding_kind(report):
    _, rows, _ = report
    assert {"named", "confounded", "unexplained", "negligible"} <= set(rows["kind"]), rows[
        ["unit", "effect", "kind"]
    ]
    conf = rows[rows["kind"] == "confounded"].iloc[0]
    assert conf["effect"] == "confounded: earth_rate, gyro_g_sensitivity"
    assert "stationary steps at two headings" in conf["separated_by"]


def test_evidence_figures_drawn_for_named_confounded_unexplained(page, report):
    facts, errors = page
    _, rows, _ = report
    assert errors == []
    shown = {t.split(" · ")[0] for t in facts["titles"]}
    for kind in ("named", "confounded", "unexplained"):
        assert set(rows.loc[rows["kind"] == kind, "effect"]) <= shown, (kind, shown)
    assert facts["evidence"] == facts["evidenceDrawn"] > 0


def test_no_table_cell_holds_json_and_numbers_are_short(page):
    facts, _ = page
    cells = facts["cells"]
    assert cells
    for text in cells:
        assert not any(tok in text for tok in ("{", "}", '":', "[", "]")), text
        # no 17-digit floats: every number has at most 6 significant digits
        for tok in text.replace(",", " ").replace(";", " ").split():
            digits = [ch for ch in tok if ch.isdigit()]
            assert len(digits) <= 8, text
    assert any(" ± " in c and "ppm/degC" in c for c in cells)  # the named effect's estimate


def test_negligible_terms_are_folded(page):
    facts, _ = page
    assert any(t.startswith("earth_rate") for t in facts["negligible"]), facts["negligible"]
