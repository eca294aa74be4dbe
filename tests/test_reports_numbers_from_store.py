"""One source of numbers: the reports show what the results store holds and compute none
of it (docs/DESIGN.md, "reports").

- A static check: no module of ``reports/`` reduces data (means, medians, spreads, sums,
  square roots, quantiles, group aggregations) or carries a statistics or unit-conversion
  constant; the reductions live in ``calib_core`` and the display factors in
  ``schemas.display``.
- End to end on a store a real run wrote (simulated fleet, the flows' store and re-flag
  steps): the summary's ``stderr_of_mean``, ``lot_median`` and ``lot_scatter`` are the
  statistics their definitions give from the parameters and summary rows (computed here
  with numpy), and the lot report shows exactly those stored numbers.
- A store written before the summary held ``stderr_of_mean`` gets it from its parameters
  on its first write (the schema migration).
"""

from __future__ import annotations

import ast
import math
import re
from pathlib import Path

import numpy as np
import pandas as pd
import pyarrow.parquet as pq
import pytest

from flows import runtime

runtime.ensure_environment()

from calib_core.outliers import OutlierConfig  # noqa: E402
from flows.fleet_sim import simulate_fleet  # noqa: E402
from flows.nightly import store_results  # noqa: E402
from flows.unit_pipeline import UnitJob, calibrate_batch  # noqa: E402
from reports.context import LotContext  # noqa: E402
from reports.lot import write_lot_report  # noqa: E402
from reports.store import StoreView  # noqa: E402
from schemas.dataset import find_sessions  # noqa: E402
from schemas.flagging import reflag_after_update  # noqa: E402
from schemas.results_store import ResultsStore  # noqa: E402

REPORTS = Path(__file__).resolve().parents[1] / "reports"
REDUCTIONS = {
    "mean",
    "nanmean",
    "median",
    "nanmedian",
    "std",
    "nanstd",
    "var",
    "nanvar",
    "sum",
    "nansum",
    "sqrt",
    "quantile",
    "percentile",
    "nanpercentile",
    "average",
    "agg",
    "aggregate",
    "transform",
    "gradient",
    "cumsum",
    "prod",
}
# 1.4826 / 0.6745: MAD to sigma; 1e3, 1e6, 3600: g -> mg, ratio -> ppm, deg/s -> deg/h
CONSTANTS = {1.4826, 0.6745, 1.2533, 1e3, 1e6, 3600.0, 57.29577951308232, 9.80665}


def _numeric_sites(path: Path) -> list[str]:
    tree = ast.parse(path.read_text(), filename=str(path))
    found = []
    for node in ast.walk(tree):
        if (
            isinstance(node, ast.Call)
            and isinstance(node.func, ast.Attribute)
            and node.func.attr in REDUCTIONS
        ):
            found.append(f"{path.name}:{node.lineno}: .{node.func.attr}(...)")
        elif (
            isinstance(node, ast.BinOp)
            and isinstance(node.op, ast.Pow)
            and not (isinstance(node.left, ast.Constant) and node.left.value == 10)
        ):  # powers of ten are decades of an axis or digits of a format
            found.append(f"{path.name}:{node.lineno}: a power (** ...)")
        elif (
            isinstance(node, ast.Constant)
            and isinstance(node.value, float | int)
            and not isinstance(node.value, bool)
            and float(node.value) in CONSTANTS
        ):
            found.append(f"{path.name}:{node.lineno}: the constant {node.value!r}")
    return found


def test_reports_reduce_no_data_and_convert_no_unit():
    modules = sorted(REPORTS.rglob("*.py"))
    assert len(modules) >= 10  # the check reads the package, not an empty glob
    sites = [s for p in modules for s in _numeric_sites(p)]
    assert not sites, "numbers computed in reports/ (compute them in calib_core, store them):\n" + "\n".join(
        sites
    )


def test_the_static_check_finds_what_it_forbids(tmp_path):
    bad = tmp_path / "bad.py"
    bad.write_text(
        "import numpy as np\n"
        "def f(v, s, df):\n"
        "    a = np.sqrt(np.sum(s**2)) / len(s)\n"
        "    b = 1.4826 * np.median(abs(v - np.median(v)))\n"
        "    return a, b, df.groupby('u')['x'].mean(), v * 1e3\n"
    )
    found = _numeric_sites(bad)
    for what in (".sqrt", ".sum", "a power", "1.4826", ".median", ".mean", "1000.0"):
        assert any(what in s for s in found), (what, found)


# --- end to end ------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def run_store(tmp_path_factory):
    """A lot of four units x four repetitions calibrated and stored as the nightly flow does
    (without Prefect: the same plain functions), re-flagged, and its report written."""
    root = tmp_path_factory.mktemp("numbers")
    simulate_fleet(root / "data", lots=1, units=4, reps=4, seed=21, sample_rate_hz=10.0)
    refs, errors = find_sessions(root / "data")
    assert refs and not errors
    by_unit: dict[tuple[str, str], list] = {}
    for r in refs:
        by_unit.setdefault((r.key.lot, r.key.unit), []).append(r)
    jobs = [UnitJob(lot, unit, rs, "new") for (lot, unit), rs in sorted(by_unit.items())]
    results = calibrate_batch(jobs, run_discovery=False)
    store = ResultsStore(root / "results")
    stored = store_results(store, results, "run-1", "test")
    assert len(stored["calibrated"]) == 4
    lot = jobs[0].lot
    reflag_after_update(store, [lot], OutlierConfig())
    path = write_lot_report(store.root, lot)
    return store, lot, path.read_text()


def test_stored_statistics_follow_their_definitions(run_store):
    store, lot, _ = run_store
    params, summary = store.read("parameters"), store.read("summary")
    assert len(summary) > 100
    key = ["unit", "model", "parameter"]
    by_key = summary.set_index(key)
    for k, g in params.groupby(key):
        row = by_key.loc[k]
        se = g["stderr"].to_numpy(float)
        se = se[np.isfinite(se)]
        want = math.sqrt(float(np.sum(se**2))) / len(se) if len(se) else math.nan
        assert row["stderr_of_mean"] == pytest.approx(want, rel=1e-12, nan_ok=True), k
        v = g["value"].to_numpy(float)
        assert row["mean"] == pytest.approx(float(np.mean(v)), rel=1e-12, abs=1e-15), k
    for (model, name), g in summary.groupby(["model", "parameter"]):
        m = g["mean"].to_numpy(float)
        m = m[np.isfinite(m)]
        if not len(m):
            continue
        med = float(np.median(m))
        mad = float(np.median(np.abs(m - med)))
        assert g["lot_median"].nunique() == 1 and g["lot_median"].iloc[0] == pytest.approx(med, rel=1e-12)
        if mad > 0:  # 4 units: the scatter is 1.4826 MAD
            assert g["lot_scatter"].iloc[0] == pytest.approx(1.4826 * mad, rel=1e-12), (model, name)


def _cells(html: str, row_start: str) -> list[str]:
    row = re.search(re.escape(row_start) + r"(.*?)</tr>", html, re.S)
    assert row, row_start
    return re.findall(r"<td[^>]*>([^<]*)</td>", row.group(1))


def test_the_lot_report_shows_the_stored_numbers(run_store):
    store, lot, html = run_store
    summary = store.read("summary")
    ctx = LotContext.load(StoreView(store.root), lot)
    # the gyro key-parameter table: its "lot median" and "lot scatter" rows under it
    panel = html[html.index('id="kp-gyro"') :]
    panel = panel[: panel.index("</table>")]
    names = [f"k_g{i}{j}" for i in (1, 2, 3) for j in (1, 2, 3)] + ["w0_x", "w0_y", "w0_z"]
    med = _cells(panel, '<tr class="lotstat"><td class="text">lot median</td>')[2:]
    sct = _cells(panel, '<tr class="lotstat"><td class="text">lot scatter</td>')[2:]
    g = summary[summary["model"] == "gyro"].set_index("parameter")
    for k, n in enumerate(names):
        stored_med = float(g.loc[n, "lot_median"].iloc[0])
        stored_sct = float(g.loc[n, "lot_scatter"].iloc[0])
        assert math.isfinite(stored_med) and math.isfinite(stored_sct), n
        assert med[k] == ctx.value("gyro", n, stored_med), n
        assert sct[k] == ctx.info("gyro", n).spread(stored_sct), n
    # each unit's Table 1: average, spread and stderr of the average are its summary row's
    for unit in ctx.units:
        block = html[html.index(f'id="unit-{unit}"') :]
        row = summary[(summary["unit"] == unit) & (summary["model"] == "gyro")].set_index("parameter")
        for n, label in (("k_g11", "k<sub>g11</sub>"), ("w0_z", "ω<sub>0z</sub>")):
            info = ctx.info("gyro", n)
            avg, spread, se = _cells(block, f'<td class="text">{label}</td>')[-3:]
            assert avg == ctx.value("gyro", n, row.loc[n, "mean"]), (unit, n)
            assert spread == info.spread(row.loc[n, "std"]), (unit, n)
            assert se == info.spread(row.loc[n, "stderr_of_mean"]), (unit, n)
            assert "—" not in (avg + spread + se)  # every one of them stored


def test_an_older_store_gets_stderr_of_mean_from_its_parameters(run_store, tmp_path):
    store, lot, _ = run_store
    import shutil

    old = ResultsStore(tmp_path / "old")
    shutil.copytree(store.root / "tables", old.root / "tables")
    shutil.copy(store.format_path, old.format_path)
    path = old.partitions("summary")[lot]
    table = pq.read_table(path)
    want = table.column("stderr_of_mean").to_numpy()
    pq.write_table(table.drop(["stderr_of_mean"]), path)  # as written before it was stored
    assert "stderr_of_mean" not in pq.read_schema(path).names
    old.write("navigation", pd.DataFrame({"lot": [lot], "unit": ["U0001"], "case": ["x"], "t": [0.0]}))
    got = pq.read_table(path).column("stderr_of_mean").to_numpy()
    np.testing.assert_allclose(got, want, rtol=1e-12)


def test_the_reports_parameter_names_are_the_fits():
    """Every parameter the reports order or title is one a fit produces (no name declared
    for a parameter that no model has), and every model the pipeline fits has its order."""
    from calib_core.models.display import param_orders
    from calib_core.models.pipeline import calibrate_repetitions

    from conftest import unit_step_means

    fitted: dict[str, list[str]] = {}
    for p in calibrate_repetitions(unit_step_means(1, 7))[0].calibration.parameters():
        fitted.setdefault(p.model, []).append(p.name)
    orders = param_orders()
    assert set(orders) == set(fitted)
    for model, names in orders.items():
        assert sorted(names) == sorted(fitted[model]), model
