"""Lot, unit and fleet reports built from a synthetic results store (no browser): files in
the right places, self-contained, flags in the right cells, missing tables tolerated."""

from __future__ import annotations

import re
from html.parser import HTMLParser

import numpy as np
import pytest
from plotly.offline import get_plotlyjs

from reports.html import decimals_for, decimate, display_unit, fmt
from reports.index import write_fleet_index
from reports.lot import ReportError, write_lot_report
from reports.unit import write_unit_report
from tools.synthetic_store import build_synthetic_store


@pytest.fixture(scope="module")
def lot_store(tmp_path_factory):
    root = tmp_path_factory.mktemp("store")
    truth = build_synthetic_store(root, n_units=12, n_outliers=2, n_failed=1, seed=11, nav_samples=4000)
    return truth


@pytest.fixture(scope="module")
def lot_html(lot_store):
    path = write_lot_report(lot_store.root, lot_store.lot)
    return path, path.read_text()


class KeyTableCells(HTMLParser):
    """(unit, param, flagged, title) of every parameter cell of the key-parameter tables (one
    per model)."""

    def __init__(self) -> None:
        super().__init__()
        self.in_table = False
        self.unit = None
        self.cells: list[tuple[str, str, bool, str]] = []

    def handle_starttag(self, tag, attrs):
        a = dict(attrs)
        if tag == "table" and "key-parameters" in (a.get("class") or "").split():
            self.in_table = True
        elif self.in_table and tag == "tr":
            self.unit = a.get("data-unit")
        elif self.in_table and tag == "td" and a.get("data-param") and self.unit:
            self.cells.append(
                (self.unit, a["data-param"], "flagged" in (a.get("class") or ""), a.get("title", ""))
            )

    def handle_endtag(self, tag):
        if tag == "table":
            self.in_table = False


def test_lot_report_is_self_contained_with_plotly_once(lot_store, lot_html):
    path, text = lot_html
    assert path == lot_store.root / "reports" / f"{lot_store.lot}.html"
    js = get_plotlyjs()
    assert text.count(js) == 1, "plotly.js must be embedded exactly once"
    assert text.count("plotly.js v") == 1
    rest = text.replace(js, "")
    # no URL anywhere outside plotly.js itself (whose inert map-tile URLs are not loaded)
    assert not re.search(r"https?://", rest), re.search(r".{60}https?://.{60}", rest)
    assert not re.search(r"""(src|href)\s*=\s*["']?(https?:|//)""", rest)
    n_specs = len(re.findall(r'<script type="application/json" id="fig\d+-spec">', text))
    n_divs = len(re.findall(r'<div class="figure" id="fig\d+"', text))
    # 4 strip plots + residual overview + 2 residual plots per unit (the synthetic store has
    # no discovery evidence series: no evidence figures)
    assert n_specs == n_divs == 4 + 1 + 2 * 12


def test_lot_report_marks_exactly_the_injected_outliers(lot_store, lot_html):
    text = lot_html[1]
    p = KeyTableCells()
    p.feed(text)
    assert len(p.cells) == 12 * (12 + 12 + 15 + 9)  # every unit x key parameter
    flagged = {(u, prm) for u, prm, f, _ in p.cells if f}
    injected = {(u, prm) for u, pairs in lot_store.outliers.items() for _, prm in pairs}
    assert flagged == injected
    for _, _, f, title in p.cells:
        if f:
            assert "FLAGGED" in title and "robust z" in title
    # the flagged units are named in the header and carry a badge in their table rows (one
    # row per model table)
    for unit in lot_store.outliers:
        assert re.search(rf'<tr class="flagged-unit" data-unit="{unit}">', text)
    flagged_rows = re.findall(r'<tr class="flagged-unit" data-unit="([^"]+)"', text)
    assert sorted(set(flagged_rows)) == sorted(lot_store.outliers)
    assert len(flagged_rows) == 4 * len(lot_store.outliers)


def test_lot_report_lists_failed_sessions_with_reasons(lot_store, lot_html):
    text = lot_html[1]
    ((unit, rep),) = lot_store.failed
    block = text[text.index("Failed sessions (1)") :]
    assert f'data-unit="{unit}"' in block[:3000]
    assert "E_MISSING_COLUMN" in block[:3000] and "required column" in block[:3000]


def test_lot_report_numbers_carry_units_and_precision(lot_store, lot_html):
    text = lot_html[1]
    # f0 is stored in g, shown in mg; w0 in deg/s
    assert re.search(r"f<sub>0x</sub>[^<]*<br><small>mg</small>", text)
    assert re.search(r"ω<sub>0z</sub>[^<]*<br><small>deg/s</small>", text)
    # k_g11 of U001: repetition spread ~3e-5 -> 6 decimals (2 significant digits of spread)
    cell = re.search(r'data-unit="U001">.*?data-param="k_g11"[^>]*>([^<]+)<', text, re.S).group(1)
    assert re.fullmatch(r"\d\.\d{6}", cell), cell


def drop_table(root, name):
    """Remove a table from a results store in either layout (format 1.0: one flat file at
    the root, as tools.synthetic_store writes it; 2.0: a directory of lot files)."""
    import shutil

    from schemas.results_store import ResultsStore

    st = ResultsStore(root)
    assert st.has_table(name)
    if st.legacy_path(name).exists():
        st.legacy_path(name).unlink()
    if st.table_dir(name).exists():
        shutil.rmtree(st.table_dir(name))
    assert not st.has_table(name)


def test_missing_tables_still_render(tmp_path):
    truth = build_synthetic_store(
        tmp_path, n_units=5, n_outliers=1, seed=3, discovery=False, navigation=False
    )
    for name in ("residuals", "compensation", "parameters"):
        drop_table(tmp_path, name)
    text = write_lot_report(tmp_path, truth.lot).read_text()
    assert "Model discovery not available" in text
    assert "Residuals not available" in text
    assert "Table 3 (compensation errors) not available" in text
    assert "Table 1 · gyroscope output model (multirate) not available" in text
    unit_text = write_unit_report(tmp_path, truth.units[0]).read_text()
    assert "Navigation drift not available" in unit_text
    drop_table(tmp_path, "summary")
    text = write_lot_report(tmp_path, truth.lot).read_text()
    assert "Key-parameter table not available" in text and "Strip plots not available" in text


def test_unknown_lot_is_an_error(lot_store):
    with pytest.raises(ReportError, match="not found"):
        write_lot_report(lot_store.root, "NO-SUCH-LOT")


def test_unit_report_and_fleet_index(lot_store, tmp_path):
    unit = next(iter(lot_store.outliers))
    path = write_unit_report(lot_store.root, unit)
    assert path == lot_store.root / "reports" / "units" / f"{unit}.html"
    text = path.read_text()
    assert text.count("plotly.js v") == 1
    assert f'id="unit-{unit}" data-unit="{unit}" open' in text
    assert "Navigation drift" in text and "History of calibrations" in text
    assert "Calibration files (3)" in text  # n_runs=3 calibration files kept
    # a second lot in the same store, then the index links to both reports
    other = build_synthetic_store(
        lot_store.root, lot="LOT-2026-11B", n_units=6, n_outliers=1, seed=12, unit_prefix="V"
    )
    write_lot_report(lot_store.root, other.lot)
    idx = write_fleet_index(lot_store.root)
    assert idx == lot_store.root / "reports" / "index.html"
    itext = idx.read_text()
    hrefs = set(re.findall(r'href="([^"#]+\.html)', itext))
    assert {f"{lot_store.lot}.html", f"{other.lot}.html", f"units/{unit}.html"} <= hrefs
    for h in hrefs:
        assert (idx.parent / h).exists(), h
    assert itext.count('name="trend ') == 4


def test_display_units_and_precision():
    assert display_unit("deg/s per deg/s") == ("", 1.0)
    assert display_unit("g") == ("mg", 1e3)
    assert display_unit("deg/s per LSB") == ("deg/s per LSB", 1.0)
    assert decimals_for(3e-5) == 6  # 2 significant digits of a 3e-5 spread
    assert decimals_for(0.012) == 3
    assert decimals_for(25.0) == 0
    assert decimals_for(float("nan")) is None
    assert fmt(-0.0123456, 4) == "\u22120.0123"
    assert fmt(float("nan")) == "\u2013"


def test_decimate_keeps_extremes_and_bounds_points():
    rng = np.random.default_rng(1)
    t = np.linspace(0, 60, 60_000)
    y = np.cumsum(rng.normal(size=t.size))
    y[31_234] = 1e4  # a one-sample spike must survive
    tx, (yx,) = decimate(t, [y], 1500)
    assert len(tx) <= 1500 + 2
    assert yx.max() == 1e4 and yx.min() == y.min()
    assert np.all(np.diff(tx) > 0) and tx[0] == t[0] and tx[-1] == t[-1]
    # lengths that do not divide into equal buckets, and NaN gaps
    for n in (4000, 4001, 60_007):
        x = np.arange(n, dtype=float)
        z = np.sin(x / 50.0)
        z[n // 3] = np.nan
        z[n - 1] = -5.0  # extreme in the last, partly padded bucket
        xd, (zd,) = decimate(x, [z], 1500)
        assert len(xd) <= 1502 and xd[-1] == n - 1 and np.nanmin(zd) == -5.0
        assert np.nanmax(zd) == np.nanmax(z)


@pytest.mark.slow
def test_fifty_unit_lot_report_stays_under_10_mb(tmp_path):
    truth = build_synthetic_store(tmp_path, n_units=50, n_reps=5, n_outliers=2, seed=50, navigation=False)
    path = write_lot_report(tmp_path, truth.lot)
    text = path.read_text()
    size = path.stat().st_size
    assert size < 10e6, f"{size / 1e6:.2f} MB"
    assert text.count("plotly.js v") == 1
    # 50 units x 2 residual figures + 4 strip plots + residual overview (the synthetic store
    # has no discovery evidence series)
    assert len(re.findall(r'<div class="figure" id="fig\d+"', text)) == 105
    # what is not plotly.js is the data: ~2.4 MB for 50 units (about 48 kB per unit)
    assert size - len(get_plotlyjs()) < 3.0e6
