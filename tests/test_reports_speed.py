"""The fast paths of the report builders (issue 7) against independent computations: the
lot-wide repetition statistics, the row formatter, the residual point order, and what the
lot report shows per unit (Table 1/2 averages, Table 3 envelopes, residual figures) checked
against the store's rows with plain pandas/numpy."""

from __future__ import annotations

import base64
import json
import re

import numpy as np
import pandas as pd
import pytest

from calib_core.figure_statistics import residual_envelope
from reports.context import LotContext, ResidualIndex
from reports.html import DASH, MINUS, fmt, td_numbers
from reports.lot import render_lot_report
from reports.store import StoreView
from reports.unit import navigation_figure
from tools.synthetic_store import build_synthetic_store


@pytest.fixture(scope="module")
def store(tmp_path_factory):
    root = tmp_path_factory.mktemp("speed-store")
    return build_synthetic_store(
        root, n_units=8, n_reps=4, n_outliers=2, n_failed=2, seed=21, nav_samples=2500
    )


@pytest.fixture(scope="module")
def lot_text(store):
    return render_lot_report(store.root, store.lot)


def _decode(a):
    if isinstance(a, dict) and "bdata" in a:
        return np.frombuffer(base64.b64decode(a["bdata"]), dtype=np.dtype(a["dtype"]).newbyteorder("<"))
    return np.asarray(a)


def _figures(text: str) -> dict[str, dict]:
    """name -> figure spec of every figure of a report."""
    out = {}
    for m in re.finditer(
        r'data-spec="(fig\d+)-spec" data-name="([^"]*)".*?'
        r'<script type="application/json" id="\1-spec">(.*?)</script>',
        text,
        re.S,
    ):
        out[m.group(2)] = json.loads(m.group(3))
    return out


def _unit_block(text: str, unit: str) -> str:
    start = text.index(f'<details class="unit" id="unit-{unit}"')
    return text[start : text.index("</details>", start)]


@pytest.mark.parametrize("decimals", [None, 0, 3, 6])
def test_td_numbers_is_fmt_per_cell(decimals):
    rng = np.random.default_rng(5)
    x = np.concatenate(
        [
            rng.normal(0, 1e-3, 20),
            rng.normal(0, 50, 20),
            [-0.0, -1e-9, 1e-9, np.nan, np.inf, -np.inf, 1.5e-7, -2.5e-12],
        ]
    )
    got = td_numbers(x.tolist(), np.isfinite(x).tolist(), decimals)
    assert got == "".join(f"<td>{fmt(v, decimals)}</td>" for v in x)
    full = x[np.isfinite(x)]
    assert td_numbers(full.tolist(), [True] * len(full), decimals) == "".join(
        f"<td>{fmt(v, decimals)}</td>" for v in full
    )
    assert MINUS in got and DASH in got and "-" not in got.replace("e-", "")


def test_residual_order_is_pandas_sort_order():
    """Ties and NaNs in the sort key: same rows in the same order as DataFrame.sort_values."""
    rng = np.random.default_rng(6)
    n = 400
    res = pd.DataFrame(
        {
            "unit": rng.choice(["U1", "U2"], n),
            "model": rng.choice(["baseline", "extended"], n),
            "test": "multirate",
            "step": rng.integers(0, 40, n),
            "channel": rng.choice(["gx", "gy", "gz", "ax"], n),
            "rate_dps": rng.choice([-30.0, 6.0, 12.0, np.nan, 300.0], n),
            "angle_deg": 0.0,
            "up_axis": "+z",
            "residual": rng.normal(size=n),
        }
    )
    a = residual_envelope(res)
    ri = ResidualIndex(a)
    for unit in ("U1", "U2"):
        d = a[a["unit"] == unit]
        d = d[(d["test"] == "multirate") & d["channel"].isin(["gx", "gy", "gz"])].sort_values("rate_dps")
        got = ri.select(unit, ri.is_gyro, ri.rate_dps)
        assert np.array_equal(got, d.index.to_numpy())
    assert ri.select("U3", ri.is_gyro, ri.rate_dps) is None


def test_repetition_tables_show_the_stored_repetitions(store, lot_text):
    """Table 1 of each unit: every repetition's value and the average, as the parameters
    table holds them (k_g11: dimensionless, 6 decimals in this lot)."""
    p = StoreView(store.root).table("parameters")
    for unit in store.units:
        rows = p[(p["unit"] == unit) & (p["model"] == "gyro") & (p["parameter"] == "k_g11")].sort_values(
            "rep"
        )
        block = _unit_block(lot_text, unit)
        row = re.search(r'<tr><td class="text">k<sub>g11</sub></td>(.*?)</tr>', block).group(1)
        cells = re.findall(r"<td[^>]*>([^<]*)</td>", row)
        vals = rows["value"].to_numpy(float)
        assert cells[1 : 1 + len(vals)] == [f"{v:.6f}" for v in vals]
        assert cells[1 + len(vals)] == f"{np.mean(vals):.6f}"
        if (unit, 3) in store.failed:
            assert "Rep 3" not in block.split("Table 2")[0]
    # flagged averages in the unit's own tables are exactly the injected outliers
    marked = {
        (u, m.group(1))
        for u in store.units
        for m in re.finditer(
            r'<tr><td class="text">([^<]+(?:<sub>[^<]+</sub>[^<]*)?)</td>'
            r'(?:(?!</tr>).)*class="avg flagged"',
            _unit_block(lot_text, u),
        )
    }
    pretty = {
        "k_g11": "k<sub>g11</sub>",
        "w0_z": "ω<sub>0z</sub>",
        "k_a22": "k<sub>a22</sub>",
        "f0_x": "f<sub>0x</sub>",
    }
    assert marked == {(u, pretty[prm]) for u, pairs in store.outliers.items() for _, prm in pairs}


def test_table3_envelopes_are_min_and_max_over_repetitions(store, lot_text):
    c = StoreView(store.root).table("compensation")
    unit = store.units[0]
    cu = c[
        (c["unit"] == unit)
        & (c["input_axis"] == "x")
        & (c["method"] == "uncompensated")
        & (c["output_axis"] == "y")
    ]
    block = _unit_block(lot_text, unit)
    row = re.search(
        r'<tr class="sep"><td class="text"><b>x</b></td><td class="text">uncompensated</td>'
        r"<td>[^<]*</td><td>([^<]*)</td>",
        block,
    ).group(1)
    assert row == f"{fmt(cu['err_min'].min(), 3)} ~ {fmt(cu['err_max'].max(), 3)}"


def test_residual_figures_hold_the_mean_and_envelope_per_step(store, lot_text):
    r = StoreView(store.root).table("residuals")
    figs = _figures(lot_text)
    for unit in (store.units[0], next(iter(store.outliers))):
        spec = figs[f"{unit} gyro residuals"]
        trace = next(t for t in spec["data"] if t["name"] == "gx error" and t["xaxis"] == "x")  # baseline
        d = r[
            (r["unit"] == unit)
            & (r["model"] == "baseline")
            & (r["test"] == "multirate")
            & (r["channel"] == "gx")
        ]
        g = (
            d.groupby("step")
            .agg(
                rate=("rate_dps", "first"),
                mean=("residual", "mean"),
                lo=("residual", "min"),
                hi=("residual", "max"),
            )
            .sort_values(["rate", "step"])
        )
        # the rates (6 to 300 deg/s) span more than a decade: a symlog axis, the rate on hover
        from reports.sections.residuals import symlog

        rate = np.array(trace["customdata"], float)
        assert np.allclose(_decode(trace["x"]), symlog(rate).astype(np.float32), rtol=1e-6)
        x, y = rate, _decode(trace["y"])
        plus, minus = _decode(trace["error_y"]["array"]), _decode(trace["error_y"]["arrayminus"])
        assert len(x) == len(g) and np.all(np.diff(x) >= 0)
        # the same set of (rate, mean, envelope) points, whatever the order among equal rates
        got = sorted(zip(x.tolist(), y.tolist(), (y + plus).tolist(), (y - minus).tolist()))
        want = sorted(
            zip(*(g[c].to_numpy(np.float32).astype(float).tolist() for c in ("rate", "mean", "hi", "lo")))
        )
        assert np.allclose(np.array(got), np.array(want), rtol=1e-6, atol=1e-9)
        accel = figs[f"{unit} accel residuals"]
        assert {t["name"] for t in accel["data"]} == {"ax error", "ay error", "az error"}
        assert all(len(t["x"]) == 18 for t in accel["data"])  # 6 faces x 3 headings


def test_per_unit_counts_match_the_sessions_table(store):
    view = StoreView(store.root)
    ctx = LotContext.load(view, store.lot)
    s = view.table("sessions")
    for unit in store.units:
        vc = s.loc[s["unit"] == unit, "status"].value_counts()
        assert ctx.session_counts(unit) == {k: int(vc.get(k, 0)) for k in ("ok", "warned", "failed")}
        n = sum(len(p) for u, p in store.outliers.items() if u == unit)
        assert ctx.n_param_flags(unit) == n
    assert ctx.session_counts("NO-SUCH-UNIT") == {"ok": 0, "warned": 0, "failed": 0}


def test_navigation_traces_in_time_order_with_extremes_kept():
    rng = np.random.default_rng(8)
    n = 4000
    t = np.linspace(0.0, 40.0, n)
    parts = []
    for case in ("static", "none"):
        v = np.cumsum(rng.normal(size=n))
        v[1234] = 500.0
        parts.append(pd.DataFrame({"case": case, "t": t, "vel_err": v, "pos_err": np.cumsum(v)}))
    nav = pd.concat(parts, ignore_index=True).sample(frac=1.0, random_state=3)  # shuffled rows
    fig = navigation_figure(nav)
    assert [tr["name"] for tr in fig["data"]] == ["uncalibrated"] * 2 + ["static calibration"] * 2
    for tr in fig["data"]:
        x, y = _decode(tr["x"]), _decode(tr["y"])
        assert len(x) <= 1502 and np.all(np.diff(x) > 0) and x[0] == np.float32(0) and x[-1] == np.float32(40)
        if tr["yaxis"] == "y":
            assert y.max() == np.float32(500.0)
