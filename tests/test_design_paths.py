"""The three newcomer paths of docs/DESIGN.md work as written: the code blocks there (an effect,
a calibration method, a report section) are run as they stand, and each plugs in through the
one line the docs name (the effect's registration, ``OPTIONAL_FITS``, the section builder)."""

from __future__ import annotations

import re
import sys
import types
from pathlib import Path

import numpy as np
import pytest

from calib_core.effects import MotionContext, SensingGeometry, catalogue, get_effect, unregister_effect
from calib_core.models import pipeline
from calib_core.results import UnitCalibration
from calib_core.sim import protocols, simulator
from calib_core.steps import SessionKey

DESIGN = Path(__file__).resolve().parents[1] / "docs" / "DESIGN.md"


def design_block(first_line: str) -> str:
    """The ```python block of DESIGN.md whose first line is ``first_line``."""
    blocks = re.findall(r"```python\n(.*?)```", DESIGN.read_text(), re.S)
    found = [b for b in blocks if b.splitlines()[0] == first_line]
    assert len(found) == 1, f"DESIGN.md has {len(found)} python blocks starting {first_line!r}"
    return found[0]


def run_block(first_line: str, name: str, namespace: dict | None = None) -> types.ModuleType:
    module = types.ModuleType(f"design_example_{name}")
    module.__dict__.update(namespace or {})
    sys.modules[module.__name__] = module  # dataclasses look their module up while defining
    try:
        exec(compile(design_block(first_line), f"DESIGN.md:{name}", "exec"), module.__dict__)
    finally:
        del sys.modules[module.__name__]
    return module


@pytest.fixture
def rate_squared_effect():
    run_block("# calib_core/effects/gyro_rate_squared.py (new)", "gyro_rate_squared")
    yield get_effect("gyro_rate_squared")
    unregister_effect("gyro_rate_squared")


def test_the_example_effect_joins_the_catalogue_and_the_plan(rate_squared_effect):
    term = rate_squared_effect
    assert "gyro_rate_squared" in catalogue()
    w = np.array([[100.0, 0, 0], [-200.0, 0, 0], [0, 0, 50.0]])
    ctx = MotionContext.from_refs(w, np.zeros((3, 3)))
    X = term.regressors(ctx, SensingGeometry.identity())
    assert X.shape == (3, 6, 3)
    # gyro x senses c_x w_x |w_x|, nothing else moves
    assert X[0, 0, 0] == 1e4 and X[1, 0, 0] == -4e4 and X[2, 2, 2] == 2500.0
    assert not X[:, 3:].any()
    # mimucal plan's design has columns for every catalogue term: the new one included
    from calib_core.discovery.plan import design

    _, columns, _ = design(protocols.to_frame(protocols.xu2016_multirate()))
    assert columns["gyro_rate_squared"].shape[1] == 3 and np.abs(columns["gyro_rate_squared"]).max() > 0


def test_the_example_method_is_fitted_stored_and_averaged_through_its_one_line(monkeypatch):
    gyro_rest = run_block("# calib_core/models/gyro_rest.py (new)", "gyro_rest")
    monkeypatch.setattr(
        pipeline, "OPTIONAL_FITS", (*pipeline.OPTIONAL_FITS, ("gyro_rest", gyro_rest.fit_gyro_rest_stack))
    )
    rng = np.random.default_rng(5)
    truth = simulator.typical_truth(rng)
    steps = protocols.default_session()
    sms = [simulator.simulate_step_means(truth, steps, rng, key=SessionKey("L1", "U1", r)) for r in (1, 2, 3)]
    fits = pipeline.calibrate_repetitions(sms)
    reps = [f.calibration for f in fits]
    # at rest w = 0, so the raw output is G = -K_g^-1 w0 (xu2016 eq. 1)
    expected = -np.linalg.solve(truth.K_g, truth.w0)
    for rep in reps:
        got = {p.name: p for p in rep.fits["gyro_rest"].parameters()}
        for a, g in zip("xyz", expected):
            p = got[f"g0_{a}"]
            assert abs(p.value - g) < 5 * p.stderr + 1e-9, (a, p, g)
    summary = {(s.model, s.name): s for s in UnitCalibration.from_reps("L1", "U1", reps).summary}
    assert summary[("gyro_rest", "g0_x")].n_reps == 3
    # a session its steps cannot determine it for: the warning the docs name, the rest fitted
    no_rest = steps[steps["test"] != "stationary"].reset_index(drop=True)
    alone = pipeline.calibrate_repetition(simulator.simulate_step_means(truth, no_rest, rng))
    assert "gyro_rest" not in alone.calibration.fits
    assert any(w.startswith("W_GYRO_REST_SKIPPED") for w in alone.calibration.warnings)


def design_diff(first_line: str) -> list[str]:
    """The lines of the ```diff block of DESIGN.md whose first line is ``first_line``."""
    blocks = re.findall(r"```diff\n(.*?)```", DESIGN.read_text(), re.S)
    found = [b.splitlines() for b in blocks if b.splitlines()[0] == first_line]
    assert len(found) == 1, f"DESIGN.md has {len(found)} diff blocks starting {first_line!r}"
    return found[0]


def test_the_example_report_section_is_one_builder_and_one_list_entry(tmp_path, monkeypatch):
    """The example runs as written (its own imports, nothing injected), and its one line in
    LOT_SECTIONS puts it in the lot report where the diff says."""
    from reports import sections
    from reports.lot import render_lot_report
    from reports.synthetic import build_synthetic_store

    diff = design_diff(" # reports/sections/__init__.py")
    real = (Path(sections.__file__)).read_text().splitlines()
    for line in diff[1:]:  # the lines the diff keeps or removes are the file's
        if line.startswith((" ", "-")) and line.strip() != "...":
            assert line[1:] in real, line
    runs = run_block("# reports/sections/runs.py (new)", "runs")
    monkeypatch.setitem(sys.modules, "reports.sections.runs", runs)
    added = [
        line[1:].strip().rstrip(",") for line in diff if line.startswith("+Section") or "+    Section" in line
    ]
    assert added == ['Section("runs", "Runs", runs.build)']
    after = next(i for i, s in enumerate(sections.LOT_SECTIONS) if s.id == "sessions")
    monkeypatch.setattr(
        sections,
        "LOT_SECTIONS",
        [
            *sections.LOT_SECTIONS[: after + 1],
            sections.Section("runs", "Runs", runs.build),
            *sections.LOT_SECTIONS[after + 1 :],
        ],
    )
    import reports.lot

    monkeypatch.setattr(reports.lot, "LOT_SECTIONS", sections.LOT_SECTIONS)
    truth = build_synthetic_store(
        tmp_path, n_units=3, n_reps=2, n_outliers=0, n_failed=0, discovery=False, navigation=False
    )
    html = render_lot_report(tmp_path, truth.lot)
    at = html.index('<section id="runs"><h2>Runs</h2>')
    assert html.index('<section id="sessions">') < at < html.index('<section id="units">')
    body = html[at : html.index("</section>", at)]
    assert body.index(">U001<") < body.index(">U002<") < body.index(">U003<")  # sorted by unit
    assert "run-20261121T020000Z" in body
    # a store without the table: the section says so instead of failing
    assert "not available" in runs.build(types.SimpleNamespace(sessions=None), None, None)
