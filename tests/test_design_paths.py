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


def test_the_example_applied_method_is_fitted_applied_and_written_through_its_one_line(monkeypatch):
    """The applied example of DESIGN.md, plugged in through its one OPTIONAL_FITS line: its
    term reaches the unit's applied Calibration and the calibration file, and applying it
    removes the g-sensitivity a simulated unit has (the truth's effect, not the fit's code,
    makes the data)."""
    from calib_core.effects import get_effect
    from schemas.unit_document import calibration_file_sections

    diffs = [b.splitlines() for b in re.findall(r"```diff\n(.*?)```", DESIGN.read_text(), re.S)]
    (diff,) = [d for d in diffs if '+    ("gyro_g_rest", gyro_g_rest.fit_gyro_g_rest_stack),' in d]
    real = Path(pipeline.__file__).read_text().splitlines()
    for line in diff[1:]:  # the lines the diff keeps are the file's
        if line.startswith(" ") and line.strip() != "...":
            assert line[1:] in real, line
    example = run_block("# calib_core/models/gyro_g_rest.py (new)", "gyro_g_rest")
    monkeypatch.setattr(
        pipeline, "OPTIONAL_FITS", (*pipeline.OPTIONAL_FITS, ("gyro_g_rest", example.fit_gyro_g_rest_stack))
    )
    rng = np.random.default_rng(11)
    G_true = np.array([[0.04, 0.0, 0.0], [0.0, 0.0, -0.03], [0.02, 0.0, 0.0]])  # deg/s per g
    truth = simulator.typical_truth(rng).with_effects((get_effect("gyro_g_sensitivity"), G_true.ravel()))
    steps = protocols.default_session()
    sms = [simulator.simulate_step_means(truth, steps, rng, key=SessionKey("L1", "U1", r)) for r in (1, 2, 3)]
    reps = [f.calibration for f in pipeline.calibrate_repetitions(sms)]
    for rep in reps:  # each repetition's estimate within its standard errors of the truth
        fit = rep.fits["gyro_g_rest"]
        assert np.all(np.abs(fit.G - G_true) < 5 * fit.stderr + 1e-4), (fit.G, fit.stderr)
    unit = UnitCalibration.from_reps("L1", "U1", reps)
    applied = pipeline.calibration_from_unit(unit)
    term = {tv.name: tv for tv in applied.terms}["gyro_g_sensitivity"]
    assert np.allclose(term.params, np.mean([r.fits["gyro_g_rest"].G for r in reps], axis=0).ravel())
    # applied: on a new session's multiposition steps the rate error no longer follows gravity
    new = simulator.simulate_step_means(truth, steps, rng, key=SessionKey("L1", "U1", 9))
    rest = new.test == "multiposition"
    without = pipeline.calibration_from_unit(unit, ())
    without = type(without)(**{**without.__dict__, "terms": ()})
    spread = lambda cal: np.std(cal.apply(new.gyro[rest], new.accel[rest])[0], axis=0)  # noqa: E731
    # (what remains, ~0.005 deg/s per gyro, is the step-to-step bias and the fit's errors;
    # without the term 0.011-0.024 deg/s)
    assert (spread(applied) ** 2).sum() < 0.2 * (spread(without) ** 2).sum(), (
        spread(applied),
        spread(without),
    )
    # the calibration file keeps it under its document key, in its unit
    doc = calibration_file_sections("L1", "U1", reps, [], [], [], None, {})
    assert np.allclose(doc["averaged"]["mean"]["gyro_g_sensitivity"], term.params.reshape(3, 3))
    assert doc["averaged"]["units"]["gyro_g_sensitivity"] == "deg/s per g"
    assert len(doc["repetitions"][0]["stderr"]["gyro_g_sensitivity"]) == 3
    # a unit whose discovery already applies the effect does not get it twice
    twice = pipeline.calibration_from_unit(unit, (term,))
    assert [tv.name for tv in twice.terms].count("gyro_g_sensitivity") == 1


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
