"""The lot report rendered in Debian's headless Chromium (DevTools protocol over a pipe):
no JavaScript error, no network request, every figure drawn, the outlier units visibly
marked in the table and in the plots (read from the DOM), a screenshot saved."""

from __future__ import annotations

import struct

import pytest

from reports.browser import Chromium, find_chromium
from reports.index import write_fleet_index
from reports.lot import write_lot_report
from reports.unit import write_unit_report

pytestmark = [
    pytest.mark.browser,
    pytest.mark.skipif(
        find_chromium() is None, reason="Debian's chromium is not installed (run tools/install-browser.sh)"
    ),
]

FLAGGED_RGB = "rgb(214, 39, 40)"  # reports.html.FLAGGED


@pytest.fixture(scope="module")
def store(synthetic_store):
    return synthetic_store


@pytest.fixture(scope="module")
def browser():
    with Chromium(width=1400, height=1000, timeout_s=120) as b:
        yield b


@pytest.fixture(scope="module")
def lot_page(store, browser):
    """The lot report loaded, every unit opened, every figure drawn."""
    path = write_lot_report(store.root, store.lot)
    browser.log.__init__()  # fresh log for this page
    browser.open(path)
    browser.wait_figures()
    top = browser.evaluate("document.querySelectorAll('.figure[data-state=rendered]').length")
    browser.evaluate("mimucalExpandAll(true)")
    browser.wait_figures()
    browser.pump(0.5)  # late console messages
    return {"path": path, "drawn_before_opening": top}


def test_no_javascript_error_and_no_network(lot_page, browser):
    assert browser.log.errors == []
    assert browser.log.requests, "the page itself should have been requested"
    assert browser.log.external_requests == [], browser.log.external_requests
    assert all(u.startswith("file:") for u in browser.log.requests)


def test_every_figure_rendered(lot_page, browser):
    facts = browser.evaluate("""(function(){
        var figs = Array.from(document.querySelectorAll('.figure'));
        return {total: figs.length,
                states: figs.map(function(f){return f.getAttribute('data-state');}),
                withSvg: figs.filter(function(f){
                    return f.querySelector('.plot-container .main-svg') !== null;}).length,
                withTraces: figs.filter(function(f){
                    return f.querySelectorAll(
                        '.scatterlayer .trace, .boxlayer .trace, .barlayer .trace').length > 0;}).length,
                attr: document.body.getAttribute('data-figures-rendered')};
    })()""")
    assert facts["total"] == 4 + 1 + 2 * 12  # the synthetic store has no discovery evidence
    assert facts["states"] == ["rendered"] * facts["total"]
    assert facts["withSvg"] == facts["total"] == facts["withTraces"]
    assert int(facts["attr"]) == facts["total"]
    # lot-level figures are drawn at load; per-unit ones only when a unit is opened
    assert lot_page["drawn_before_opening"] == 5


def test_outliers_marked_in_table(lot_page, browser, store):
    cells = browser.evaluate("""(function(){
        return Array.from(document.querySelectorAll('.key-parameters td.flagged')).map(function(td){
            var s = getComputedStyle(td);
            return {unit: td.parentElement.getAttribute('data-unit'), param: td.getAttribute('data-param'),
                    bg: s.backgroundColor, color: s.color, text: td.textContent, title: td.title};
        });
    })()""")
    normal = browser.evaluate("""(function(){
        var td = document.querySelector('.key-parameters td[data-param]:not(.flagged)');
        var s = getComputedStyle(td); return {bg: s.backgroundColor, color: s.color};
    })()""")
    injected = {(u, p) for u, pairs in store.outliers.items() for _, p in pairs}
    assert {(c["unit"], c["param"]) for c in cells} == injected
    for c in cells:
        assert c["bg"] != normal["bg"] and c["color"] != normal["color"]  # visibly different
        assert "FLAGGED" in c["title"]
    badges = browser.evaluate(
        "Array.from(document.querySelectorAll('#key-parameters-gyro tr.flagged-unit')).map(function(r){"
        "return r.getAttribute('data-unit');})"
    )
    assert sorted(badges) == sorted(store.outliers)


def test_outliers_marked_and_labelled_in_strip_plots(lot_page, browser, store):
    labels = browser.evaluate("""(function(){
        var out = [];
        document.querySelectorAll('.figure[data-name^="strip "]').forEach(function(f){
            f.querySelectorAll('.textpoint text').forEach(function(t){
                var pt = t.closest('.trace').querySelector('.points .point');
                out.push({fig: f.getAttribute('data-name'), text: t.textContent,
                          fill: pt ? pt.style.fill : null});
            });
        });
        return out;
    })()""")
    injected = {(f"strip {m}", u) for u, pairs in store.outliers.items() for m, _ in pairs}
    got = {(label["fig"], label["text"]) for label in labels}
    assert got == injected
    # one labelled red marker per flagged (unit, parameter)
    assert len(labels) == sum(len(p) for p in store.outliers.values())
    assert all(label["fill"] == FLAGGED_RGB for label in labels)


def test_sorting_by_a_parameter(lot_page, browser, store):
    # the k_g11 outlier was shifted by +0.012, far above the lot: first when sorted descending
    ((unit, _),) = [(u, p) for u, pairs in store.outliers.items() for _, p in pairs if p == "k_g11"]
    order = browser.evaluate("""(function(){
        var th = Array.from(document.querySelectorAll('#key-parameters-gyro thead tr:last-child th'))
                 .filter(function(h){return h.textContent.indexOf('g11') >= 0;})[0];
        th.click(); th.click();
        return [th.getAttribute('aria-sort'),
                Array.from(document.querySelectorAll('#key-parameters-gyro tbody tr')).map(
                    function(r){return r.getAttribute('data-unit');})];
    })()""")
    assert order[0] == "descending"
    # the lot median and scatter rows (no unit) stay last
    assert order[1][0] == unit and len(order[1]) == 12 + 2 and order[1][-2:] == [None, None]


def test_screenshot(lot_page, browser, tmp_path):
    browser.evaluate("mimucalExpandAll(false); window.scrollTo(0, 0)")
    png = browser.screenshot(tmp_path / "lot-report.png", full_page=True, max_height=6000)
    data = png.read_bytes()
    assert data[:8] == b"\x89PNG\r\n\x1a\n"
    width, height = struct.unpack(">II", data[16:24])
    assert width == 1400 and 2000 < height <= 6000
    assert len(data) > 100_000  # a real page, not a blank one


def test_unit_report_and_index_render(store, browser):
    unit = sorted(store.outliers)[0]
    pages = [write_unit_report(store.root, unit), write_fleet_index(store.root)]
    for path in pages:
        browser.log.__init__()
        browser.open(path)
        browser.wait_figures()
        browser.pump(0.3)
        total = browser.evaluate("document.querySelectorAll('.figure').length")
        drawn = browser.evaluate(
            "document.querySelectorAll('.figure[data-state=rendered] .main-svg').length > 0"
            " && document.querySelectorAll('.figure[data-state=rendered]').length"
        )
        assert total > 0 and drawn == total, (path, total, drawn)
        assert browser.log.errors == [], (path, browser.log.errors)
        assert browser.log.external_requests == []
