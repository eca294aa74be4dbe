"""Production QA end to end through the CLI (issue 20 items 1-4): the QA status travels with
the calibration, limits written with units stick until cleared, small lots are judged
against the fleet history, times are acquisition times, fingerprints are content hashes.

One fleet for the module: two lots sharing one population (so that lot L02 can be judged
against L01), L01 of 20 units and L02 cut to 6; U0003 (L01) has f0_y 12 mg (12 unit sd)
off, outside the limits the test writes in mg; U0021 (L02) has k_g11 +0.03 (10 unit sd)."""

from __future__ import annotations

import json
import re
import shutil
from pathlib import Path

import numpy as np
import pytest

from flows import runtime

runtime.ensure_environment()

from calib_core.figure_statistics import lot_trends  # noqa: E402
from calib_core.sim.simulator import typical_truth  # noqa: E402
from flows import fleet_sim  # noqa: E402
from flows.cli import main as cli_main  # noqa: E402
from reports.history import KEY_ELEMENTS, history_frame  # noqa: E402
from reports.store import StoreView  # noqa: E402
from schemas.results_store import ResultsStore  # noqa: E402

pytestmark = pytest.mark.slow

COMMON = typical_truth(np.random.default_rng(7))  # every lot's mean unit
F0_SHIFT_G = 0.012
KG_SHIFT = 0.03


def _truth(rng, lot, unit):
    from dataclasses import replace

    t = fleet_sim.unit_truth(COMMON, rng)
    if unit == "U0003":
        t = replace(t, f0=t.f0 + np.array([0.0, F0_SHIFT_G, 0.0]))
    if unit == "U0021":
        K = t.K_g.copy()
        K[0, 0] += KG_SHIFT
        t = replace(t, K_g=K)
    return t


def _qa(results: Path, unit: str) -> dict:
    path = ResultsStore(results).find_calibration(unit)
    return json.loads(path.read_text())


def _cli(capsys, *argv) -> tuple[int, str, str]:
    code = cli_main(list(map(str, argv)))
    out = capsys.readouterr()
    return code, out.out, out.err


@pytest.fixture(scope="module")
def fleet(tmp_path_factory):
    base = tmp_path_factory.mktemp("qa")
    data, results = base / "data", base / "results"
    fleet_sim.simulate_fleet(
        data, lots=2, units=20, reps=3, seed=20, sample_rate_hz=20.0, truth_factory=_truth
    )
    for d in sorted((data / "lot=L02").iterdir())[6:]:  # L02: U0021..U0026
        shutil.rmtree(d)
    f0_y_mg = COMMON.f0[1] * 1e3
    limits = base / "limits.toml"
    limits.write_text(f'[limits]\nf0_y = {{min = "{f0_y_mg - 6:.3f} mg", max = "{f0_y_mg + 6:.3f} mg"}}\n')
    code = cli_main(
        ["nightly", str(data), "--results", str(results), "--config", str(limits), "--no-discovery"]
    )
    assert code == 0
    return base, data, results


def test_limits_written_in_mg_fail_the_shifted_unit_and_the_status_travels(fleet, capsys):
    base, data, results = fleet
    doc = _qa(results, "U0003")
    qa = doc["qa"]
    assert qa["status"] == "limits" and qa["lot"] == "L01"
    assert len(qa["failed_limits"]) == 1 and "accel.f0_y" in qa["failed_limits"][0]
    assert "mg" in qa["failed_limits"][0]  # the limit as written
    # every reason: the 12 sd shift is a statistical outlier as well
    assert any(r.startswith("[robust_z] accel.f0_y") for r in qa["reasons"])
    assert qa["reference"] == "lot" and qa["config"]["limits"]
    code, out, err = _cli(capsys, "calibration", "--results", results, "--unit", "U0003")
    assert code == 4 and out == "" and "refused" in err and "limits" in err
    code, out, err = _cli(capsys, "calibration", "--results", results, "--unit", "U0003", "--allow-flagged")
    assert code == 0 and out.strip().endswith(".json") and "warning" in err
    # clean units pass; only U0003 fails the limit
    units = ResultsStore(results).read("units")
    limit_units = sorted(units.loc[units["flag_reason"].fillna("").str.contains(r"\[limit\]"), "unit"])
    assert limit_units == ["U0003"]
    code, out, _ = _cli(capsys, "calibration", "--results", results, "--unit", "U0001")
    assert code == 0 and _qa(results, "U0001")["qa"]["status"] == "pass"


def test_the_python_api_refuses_a_flagged_calibration_too(fleet):
    from schemas import api

    _, _, results = fleet
    with pytest.raises(api.FlaggedCalibration, match="U0021|k_g11"):
        api.load_calibration_for(results, unit="U0021")
    assert api.load_calibration_for(results, unit="U0021", allow_flagged=True) is not None
    assert api.load_calibration_for(results, unit="U0001") is not None  # pass


def test_small_lot_is_judged_against_the_fleet_history_and_the_report_says_so(fleet, capsys):
    base, data, results = fleet
    qa = _qa(results, "U0021")["qa"]
    assert qa["status"] == "flagged" and qa["reference"] == "fleet history"
    # L01's 20 units but U0003, which failed a limit
    assert "19 good units" in qa["reference_detail"] and "(L01)" in qa["reference_detail"]
    assert any("gyro.k_g11" in r for r in qa["reasons"])
    flagged = set(ResultsStore(results).read("units").query("lot == 'L02' and flagged")["unit"])
    assert flagged == {"U0021"}  # the clean units of the small lot stay clean
    html = (results / "reports" / "L02.html").read_text()
    assert "fleet history" in html and "Reference:" in html
    code, _, _ = _cli(capsys, "calibration", "--results", results, "--unit", "U0021")
    assert code == 4


def _values(a) -> np.ndarray:
    """A plotly array: a list, or a typed array {dtype, bdata (base64)}."""
    if isinstance(a, dict):
        import base64

        return np.frombuffer(base64.b64decode(a["bdata"]), dtype=a["dtype"])
    return np.asarray(a, float)


def _figures(html: str) -> dict[str, dict]:
    """The report's figure specs by their data-name."""
    out = {}
    for name, fid in re.findall(
        r'data-name="([^"]*)"[^>]*></div><script type="application/json" '
        r'id="(fig\d+)-spec">',
        html,
    ):
        m = re.search(rf'id="{fid}-spec">(.*?)</script>', html, re.S)
        out[name] = json.loads(m.group(1))
    return out


def test_report_shows_limits_on_the_box_plot_and_separate_badges(fleet):
    _, _, results = fleet
    html = (results / "reports" / "L01.html").read_text()
    assert 'class="badge limit"' in html and "limit failed" in html
    fig = _figures(html)["strip accel"]
    f0_y_mg = COMMON.f0[1] * 1e3
    # the dashed lines at the limits, in the report's unit (mg), on the f0_y panel
    lines = [
        (sh["yref"], sh["y0"])
        for sh in fig["layout"]["shapes"]
        if sh.get("type") == "line" and sh.get("line", {}).get("dash") == "dash"
    ]
    assert sorted(y for _, y in lines) == pytest.approx([f0_y_mg - 6, f0_y_mg + 6], abs=1e-3)
    assert len({ref for ref, _ in lines}) == 1
    # every box holds all 20 units, the flagged U0003 included; U0003 is a labelled limit
    # failure (a cross), no unit of L01 is drawn as an outlier diamond on f0_y
    boxes = [t for t in fig["data"] if t.get("type") == "box"]
    assert boxes and all(len(_values(t["y"])) == 20 for t in boxes)
    limit_pts = [t for t in fig["data"] if t.get("name") == "limit failed" and t.get("text")]
    assert [t["text"] for t in limit_pts] == [["U0003"]]
    assert limit_pts[0]["yaxis"] == next(ref for ref, _ in lines)
    assert any(t.get("name") == "acceptance limit" for t in fig["data"])


def test_limits_stick_for_later_runs_until_cleared(fleet, capsys):
    base, data, results = fleet
    code, out, err = _cli(capsys, "rerun", data, "--results", results, "--unit", "U0004", "--no-discovery")
    assert code == 0
    assert _qa(results, "U0003")["qa"]["status"] == "limits"  # no --config: still applied
    unit_html = (results / "reports" / "units" / "U0004.html").read_text()
    assert 'class="qa-status"' in unit_html and '<span class="badge ok">pass</span>' in unit_html
    assert ResultsStore(results).read_qa_config() is not None
    code, out, err = _cli(capsys, "report", "--results", results, "--lot", "L01", "--config", "none")
    assert code == 0 and ResultsStore(results).read_qa_config() is None
    doc = _qa(results, "U0003")
    assert doc["qa"]["status"] == "flagged"  # the robust z remains, the limit is gone
    assert doc["qa"]["failed_limits"] == []
    assert [h["status"] for h in doc["qa_history"]] == ["limits"]


def test_apply_refuses_another_units_raw_file_unless_forced(fleet, tmp_path, capsys):
    _, data, results = fleet
    cal = ResultsStore(results).find_calibration("U0001")
    raw = data / "lot=L01" / "unit=U0002" / "rep=1" / "samples.parquet"
    code, out, err = _cli(capsys, "apply", cal, raw, tmp_path / "x.parquet")
    assert code == 2 and "U0002" in err and "U0001" in err
    assert not (tmp_path / "x.parquet").exists()
    code, out, err = _cli(capsys, "apply", cal, raw, tmp_path / "x.parquet", "--force")
    assert code == 0 and (tmp_path / "x.parquet").exists()


def test_acquisition_time_drives_at_trends_and_a_copy_is_unchanged(fleet, capsys, tmp_path):
    base, data, results = fleet
    # sessions of L01 were acquired on 2026-11-20 (the calibrations were produced today)
    code, out, err = _cli(
        capsys, "calibration", "--results", results, "--unit", "U0001", "--at", "2026-11-20"
    )
    assert code == 0 and out.strip().endswith(".json")
    code, out, err = _cli(
        capsys, "calibration", "--results", results, "--unit", "U0001", "--at", "2026-11-19"
    )
    assert code == 2 and "no calibration at or before 2026-11-19T23:59:59" in err
    assert "session_start" in err  # the time it goes by
    # after the rerun of U0004 the lot's trend point is the median over all 20 units
    view = StoreView(results)
    tr = lot_trends(history_frame(view), [e[1] for e in KEY_ELEMENTS]).set_index("lot")
    assert tr.loc["L01", "n_units"] == 20 and tr.loc["L02", "n_units"] == 6
    summary = ResultsStore(results).read("summary")
    kg = summary.query("lot == 'L01' and model == 'gyro' and parameter == 'k_g11'")["mean"]
    assert tr.loc["L01", "k_g11"] == pytest.approx(float(np.median(kg)), abs=1e-12)
    assert tr.loc["L01", "time"] < tr.loc["L02", "time"]  # L01 acquired first
    assert (tr.loc["L01", "time"].strftime("%Y-%m-%d"), tr.loc["L02", "time"].strftime("%Y-%m-%d")) == (
        "2026-11-20",
        "2026-11-21",
    )
    # a copied dataset: no unit recalibrated, no calibration file added
    files = sorted((results / "calibrations").rglob("*.json"))
    copy = tmp_path / "copy"
    shutil.copytree(data, copy)
    code, out, err = _cli(capsys, "nightly", copy, "--results", results, "--no-discovery")
    assert code == 0 and "(0 calibrated, 26 unchanged" in out + err
    assert sorted((results / "calibrations").rglob("*.json")) == files


@pytest.mark.browser
def test_lot_report_in_the_browser_draws_the_limits_and_both_badges(fleet):
    from reports.browser import Chromium, find_chromium

    if find_chromium() is None:
        pytest.skip("Debian's chromium is not installed (run tools/install-browser.sh)")
    base, _, results = fleet
    # the limits again (an earlier test cleared them): the report is rebuilt with them
    assert (
        cli_main(["report", "--results", str(results), "--lot", "L01", "--config", str(base / "limits.toml")])
        == 0
    )
    with Chromium(width=1400, height=1000, timeout_s=120) as b:
        b.open(results / "reports" / "L02.html")
        b.wait_figures()
        b.open(results / "reports" / "L01.html")
        b.wait_figures()
        b.pump(0.3)
        assert b.log.errors == []
        facts = b.evaluate("""(function(){
          const fig = document.querySelector('.figure[data-name="strip accel"]');
          const dashed = [...fig.querySelectorAll('.shapelayer path')]
            .filter(p => (p.style.strokeDasharray || '') !== '');
          const badge = document.querySelector('.badge.limit');
          return {state: fig.dataset.state, dashed: dashed.length,
                  limitBadge: badge ? getComputedStyle(badge).backgroundColor : null,
                  limitText: badge ? badge.textContent : null,
                  reference: document.querySelector('.qa-reference').textContent};
        })()""")
    assert facts["state"] == "rendered"
    assert facts["dashed"] == 2  # min and max of f0_y
    assert facts["limitBadge"] == "rgb(180, 83, 9)" and "limit failed" in facts["limitText"]
    assert "Reference:" in facts["reference"] and "f0_y" in facts["reference"]
