"""Reports people can scan and archive (issue 20 item 7), in Debian's headless chromium: the
key-parameter tables behind a model chooser, flagged units first, the unit column frozen,
spreads in ppm / deg/h / mg, the symlog rate axis of gyro error vs rate, the print style,
and the PDF of a lot report."""

from __future__ import annotations

import re

import numpy as np
import pytest

from reports.browser import Chromium, find_chromium
from reports.lot import write_lot_report
from reports.sections.residuals import rates_span_decades, symlog, symlog_axis


def test_symlog_is_monotonic_signed_and_its_ticks_name_the_rates():
    x = np.array([-3600, -100, -6, -1, 0, 1, 6, 100, 3600], float)
    y = symlog(x)
    assert np.all(np.diff(y) > 0) and y[4] == 0 and np.allclose(y, -y[::-1])
    # a decade of rate is (nearly) one unit of axis far from the linear zone
    assert abs((symlog(np.array([1000.0])) - symlog(np.array([100.0])))[0] - 1) < 0.01
    ax = symlog_axis(3600)
    assert ax["ticktext"] == [
        "\u221210000",
        "\u22121000",
        "\u2212100",
        "\u221210",
        "\u22121",
        "0",
        "1",
        "10",
        "100",
        "1000",
        "10000",
    ]
    assert np.allclose(ax["tickvals"], symlog(np.array([-1e4, -1e3, -100, -10, -1, 0, 1, 10, 100, 1e3, 1e4])))
    assert rates_span_decades(np.array([6, -6, 3600, 0.0]))
    assert not rates_span_decades(np.array([50, -50, 200, 0.0]))


@pytest.fixture(scope="module")
def store(synthetic_store):
    return synthetic_store


@pytest.fixture(scope="module")
def page(store):
    path = write_lot_report(store.root, store.lot)
    with Chromium(width=1400, height=1000, timeout_s=120) as b:
        b.open(path)
        b.wait_figures()
        yield b, path


def visible_panels(b) -> list[str]:
    return b.evaluate(
        "Array.from(document.querySelectorAll('.tabpanel'))"
        ".filter(function(p){return p.offsetParent !== null;})"
        ".map(function(p){return p.getAttribute('data-model');})"
    )


@pytest.mark.browser
@pytest.mark.skipif(find_chromium() is None, reason="Debian's chromium is not installed")
def test_one_table_per_model_behind_a_chooser(page, store):
    b, _ = page
    assert visible_panels(b) == ["gyro"]
    tabs = b.evaluate(
        "Array.from(document.querySelectorAll('#key-parameter-tabs [role=tab]'))"
        ".map(function(t){return [t.getAttribute('data-tab'), t.textContent];})"
    )
    assert [t for t, _ in tabs] == ["kp-gyro", "kp-accel", "kp-accel_static", "kp-lever_arm"]
    # each tab says how many flagged cells its table holds
    injected = {}
    for _, pairs in store.outliers.items():
        for m, _p in pairs:
            injected[m] = injected.get(m, 0) + 1
    for tid, text in tabs:
        n = injected.get(tid[3:], 0)
        assert (f"{n} \u2691" in text) == bool(n), (tid, text)
    b.evaluate("document.getElementById('kp-accel-tab').click()")
    assert visible_panels(b) == ["accel"]
    # a table of one model has that model's columns only (12 of 51 before)
    n_cols = b.evaluate("document.querySelectorAll('#key-parameters-accel thead tr:last-child th').length")
    assert n_cols == 3 + 12
    b.evaluate("document.getElementById('kp-gyro-tab').click()")
    assert visible_panels(b) == ["gyro"]


@pytest.mark.browser
@pytest.mark.skipif(find_chromium() is None, reason="Debian's chromium is not installed")
def test_flagged_units_first_and_the_unit_column_frozen(page, store):
    b, _ = page
    for model in ("gyro", "accel", "accel_static", "lever_arm"):
        order = b.evaluate(
            f"Array.from(document.querySelectorAll('#key-parameters-{model} tbody tr[data-unit]'))"
            ".map(function(r){return [r.getAttribute('data-unit'), "
            "r.classList.contains('flagged-unit')];})"
        )
        flags = [f for _, f in order]
        n = sum(flags)
        assert n == len(store.outliers) and flags == [True] * n + [False] * (len(order) - n), model
        # within this model, the units with a flagged cell of this model come first
        here = sorted(u for u, pairs in store.outliers.items() if any(m == model for m, _ in pairs))
        assert [u for u, _ in order[: len(here)]] == here
    # scroll the gyro table right: the unit cells stay at the left edge, the values move
    moved = b.evaluate("""(function(){
        var t = document.getElementById('key-parameters-gyro');
        var wrap = t.parentElement;
        var unit = t.tBodies[0].rows[0].cells[0], val = t.tBodies[0].rows[0].cells[8];
        var u0 = unit.getBoundingClientRect().left, v0 = val.getBoundingClientRect().left;
        wrap.style.maxWidth = '600px';
        wrap.scrollLeft = 400;
        var r = [u0, unit.getBoundingClientRect().left, v0, val.getBoundingClientRect().left,
                 wrap.scrollLeft, getComputedStyle(unit).position];
        wrap.scrollLeft = 0; wrap.style.maxWidth = '';
        return r;
    })()""")
    u0, u1, v0, v1, scrolled, position = moved
    assert scrolled > 100 and position == "sticky"
    assert abs(u1 - u0) < 1.0 and v0 - v1 > 100


@pytest.mark.browser
@pytest.mark.skipif(find_chromium() is None, reason="Debian's chromium is not installed")
def test_spreads_in_ppm_deg_per_hour_and_mg(page):
    b, _ = page
    rows = b.evaluate("""(function(){
        var out = {};
        ['gyro', 'accel'].forEach(function(m){
            var t = document.getElementById('key-parameters-' + m);
            var heads = Array.from(t.tHead.rows[t.tHead.rows.length - 1].cells)
                .map(function(h){return h.textContent;});
            var stat = Array.from(t.tBodies[0].rows)
                .filter(function(r){return r.classList.contains('lotstat');});
            out[m] = {heads: heads,
                      scatter: Array.from(stat[1].cells).map(function(c){return c.textContent;})};
        });
        return out;
    })()""")
    g, a = rows["gyro"], rows["accel"]
    col = {h.split()[0] if h else h: i for i, h in enumerate(g["heads"])}
    sc = dict(zip(g["heads"], g["scatter"]))
    assert g["scatter"][0] == "lot scatter"
    for h, v in sc.items():
        if h.startswith("kg"):
            assert re.fullmatch(r"[\d.]+\u00a0ppm", v), (h, v)
        if h.startswith("ω0"):
            assert re.fullmatch(r"[\d.]+\u00a0deg/h", v), (h, v)
    for h, v in zip(a["heads"], a["scatter"]):
        if h.startswith("f0"):
            assert re.fullmatch(r"[\d.]+\u00a0mg", v), (h, v)
    assert col  # the headings were read
    # no spread in scientific notation anywhere in the tables (8.8e-06 before)
    text = b.evaluate(
        "Array.from(document.querySelectorAll('td.spread, tr.lotstat td'))"
        ".map(function(c){return c.textContent;}).join(' ')"
    )
    assert not re.search(r"\de[-+]\d", text)


@pytest.mark.browser
@pytest.mark.skipif(find_chromium() is None, reason="Debian's chromium is not installed")
def test_gyro_error_vs_rate_on_a_symlog_axis(page, store):
    b, _ = page
    b.evaluate("mimucalExpandAll(true)")
    b.wait_figures()
    ax = b.evaluate("""(function(){
        var f = document.querySelector('.figure[data-name$="gyro residuals"]');
        var xa = f._fullLayout.xaxis;
        var xs = [].concat.apply([], f._fullData.map(function(t){return Array.from(t.x);}));
        return {ticktext: xa.ticktext, type: xa.type, title: xa.title.text,
                min: Math.min.apply(null, xs), max: Math.max.apply(null, xs),
                hover: f.data[0].hovertemplate, custom: Array.from(f.data[0].customdata || [])};
    })()""")
    assert "symmetric log" in ax["title"] and "100" in ax["ticktext"] and "\u2212100" in ax["ticktext"]
    # the drawn x is symlog of the rates; the hover shows the rate itself
    rates = np.array(ax["custom"], float)
    assert np.abs(rates).min() <= 10 and np.abs(rates).max() >= 100 and "customdata" in ax["hover"]
    assert ax["max"] == pytest.approx(float(symlog(np.array([np.abs(rates).max()]))[0]), rel=1e-5)
    b.evaluate("mimucalExpandAll(false)")


@pytest.mark.browser
@pytest.mark.skipif(find_chromium() is None, reason="Debian's chromium is not installed")
def test_print_style_shows_every_model_table(page):
    b, _ = page
    b.send("Emulation.setEmulatedMedia", session=True, media="print")
    try:
        shown = visible_panels(b)
        tabs = b.evaluate("getComputedStyle(document.getElementById('key-parameter-tabs')).display")
    finally:
        b.send("Emulation.setEmulatedMedia", session=True, media="")
    assert shown == ["gyro", "accel", "accel_static", "lever_arm"] and tabs == "none"
    assert visible_panels(b) == ["gyro"]


@pytest.mark.browser
@pytest.mark.skipif(find_chromium() is None, reason="Debian's chromium is not installed")
def test_lot_report_prints_to_pdf(page, tmp_path):
    from reports.pdf import print_pdf

    _, html = page
    pdf = print_pdf(html, tmp_path / "lot.pdf")
    data = pdf.read_bytes()
    assert data[:5] == b"%PDF-" and data.rstrip().endswith(b"%%EOF")
    pages = len(re.findall(rb"/Type\s*/Page[^s]", data))
    assert pages >= 3 and len(data) > 100_000, (pages, len(data))
