"""Noise in the fleet run, end to end on a simulated lot (issue 31's done-when): ten units
with a static noise recording each, one of them with three times the lot's angle random
walk, one without a recording (its noise from the static steps), calibrated and stored as
the nightly does (the flows' plain functions, without Prefect), re-flagged, reported.

- the noisy unit is flagged for noise, with its reason, and no other unit is;
- the ``noise`` and ``noise_allan`` tables read as one table in pandas, pyarrow.dataset and
  DuckDB;
- each unit's white coefficients match the simulator's truth (white noise per sample of
  known sd: angle random walk = sd / sqrt(rate) * 60 deg/sqrt(h));
- the unit without a recording: white determined from its static steps, the slower
  processes null with the reason;
- the calibration file carries the noise model;
- the lot report's Noise section shows the curves, the flagged unit in red (and in
  Chromium, when it is installed)."""

from __future__ import annotations

import json
import math
import shutil

import duckdb  # a test dependency (pyproject.toml)
import numpy as np
import pandas as pd
import pyarrow.dataset as ds
import pytest

from flows import runtime

runtime.ensure_environment()

from flows.fleet_sim import simulate_fleet  # noqa: E402
from flows.nightly import store_results  # noqa: E402
from flows.unit_pipeline import calibrate_batch  # noqa: E402
from reports.lot import write_lot_report  # noqa: E402
from schemas.dataset import find_sessions  # noqa: E402
from schemas.flagging import reflag_after_update  # noqa: E402
from schemas.limits import config_from_toml  # noqa: E402
from schemas.results_store import ResultsStore  # noqa: E402
from schemas.unit_plan import plan_unit_jobs  # noqa: E402

RATE_HZ = 10.0
RECORDING_S = 900.0
LIMITS = '[limits]\ngyro_white = {max = "2.5 deg/sqrt(h)"}\n'


@pytest.fixture(scope="module")
def lot(tmp_path_factory):
    root = tmp_path_factory.mktemp("noisefleet")
    manifest = simulate_fleet(
        root / "data",
        lots=1,
        units=10,
        reps=2,
        seed=31,
        sample_rate_hz=RATE_HZ,
        noise_recording_s=RECORDING_S,
        noisy_units=1,
        noise_factor=3.0,
    )
    noisy = manifest["noise"]["noisy_units"][0]["unit"]
    quiet = [u["unit"] for u in manifest["units"] if u["unit"] != noisy]
    static_unit = quiet[-1]  # its recording removed: the static steps measure it
    shutil.rmtree(root / "data" / "lot=L01" / f"unit={static_unit}" / "noise")
    refs, errors = find_sessions(root / "data")
    assert refs and not errors
    jobs, _, _ = plan_unit_jobs(refs, {})
    results = calibrate_batch(jobs, run_discovery=False)
    store = ResultsStore(root / "results")
    store_results(store, results, "run-1", "test")
    cfg = config_from_toml(LIMITS)
    lot_flags, _ = reflag_after_update(store, ["L01"], cfg)
    report = write_lot_report(store.root, "L01")
    return {
        "root": root,
        "store": store,
        "manifest": manifest,
        "noisy": noisy,
        "static_unit": static_unit,
        "results": results,
        "flags": lot_flags,
        "report": report,
    }


def test_the_noisy_unit_is_flagged_for_noise_and_no_other(lot):
    store = lot["store"]
    noise = store.read("noise")
    flagged = noise[noise["flagged"].astype(bool)]
    assert set(flagged["unit"]) == {lot["noisy"]}
    # its gyro white noise, three times the lot's, against the lot and against the limit
    assert set(flagged["coefficient"]) == {"white"} and set(flagged["channel"]) <= {"gx", "gy", "gz"}
    reasons = "; ".join(flagged["flag_reason"])
    assert "[noise]" in reasons and "x the lot median" in reasons and "[limit]" in reasons
    units = store.read("units").set_index("unit")
    assert units.loc[lot["noisy"], "flagged"] and "[noise]" in units.loc[lot["noisy"], "flag_reason"]
    assert not units.drop(index=lot["noisy"])["flagged"].any()
    assert {f.unit for lf in lot["flags"] for f in lf.flags} == {lot["noisy"]}


def test_noise_tables_read_as_one_table_three_ways(lot):
    store = lot["store"]
    for name in ("noise", "noise_allan"):
        d = store.table_dir(name)
        df = pd.read_parquet(d)
        t = ds.dataset(d, format="parquet").to_table()
        n_duck = duckdb.sql(f"select count(*) from read_parquet('{d}/*.parquet')").fetchall()[0][0]
        assert len(df) == t.num_rows == n_duck > 0, name
        assert set(df["unit"]) == {u["unit"] for u in lot["manifest"]["units"]}
    # a question a quality engineer would ask in SQL: the gyro angle random walk per unit
    arw = duckdb.sql(
        f"select unit, max(value) as arw from read_parquet('{store.table_dir('noise')}/*.parquet') "
        "where coefficient = 'white' and channel in ('gx', 'gy', 'gz') group by unit order by arw desc"
    ).fetchall()
    assert arw[0][0] == lot["noisy"] and len(arw) == 10


def test_white_coefficients_match_the_simulated_truth(lot):
    noise = lot["store"].read("noise")
    white = noise[(noise["coefficient"] == "white") & noise["channel"].isin(["gx", "gy", "gz"])]
    inside = []
    for u in lot["manifest"]["units"]:
        sd = np.asarray(u["truth_white_sd"] if "truth_white_sd" in u else _white_sd(u), float)
        truth = sd / math.sqrt(RATE_HZ) * 60.0  # deg/sqrt(h)
        rows = white[white["unit"] == u["unit"]].sort_values("channel")
        assert len(rows) == 3
        got = rows["value"].to_numpy(float)
        # estimates within 10 % of the truth, and the intervals cover it on most channels
        np.testing.assert_allclose(got, truth, rtol=0.10, err_msg=u["unit"])
        inside += list((rows["lo"].to_numpy(float) <= truth) & (truth <= rows["hi"].to_numpy(float)))
    assert np.mean(inside) >= 0.8, np.mean(inside)


def _white_sd(unit_doc):
    rec = unit_doc.get("noise_recording")
    if rec is not None:
        return rec["gyro_white_sd_dps"]
    # the unit without a recording: the lot's white sd per sample (the simulator's default)
    return [0.05, 0.05, 0.05]


def test_without_a_recording_the_static_steps_give_the_white_noise_only(lot):
    noise = lot["store"].read("noise")
    rows = noise[noise["unit"] == lot["static_unit"]]
    assert rows["source"].str.startswith("static steps").all()
    white = rows[rows["coefficient"] == "white"]
    assert white["value"].notna().all() and len(white) == 6
    slow = rows[rows["coefficient"].isin(["bias_instability", "random_walk", "ramp"])]
    assert len(slow) and slow["value"].isna().all()
    assert slow["reason"].str.contains("static steps").all()
    # the others were measured on their recordings
    others = noise[noise["unit"] != lot["static_unit"]]
    assert others["source"].eq("recording static").all()


def test_the_calibration_file_carries_the_noise_model(lot):
    store = lot["store"]
    units = store.read("units").set_index("unit")
    doc = json.loads((store.root / units.loc[lot["noisy"], "calibration_file"]).read_text())
    noise = doc["noise"]
    assert noise["source"] == "recording static" and noise["rate_hz"] == RATE_HZ
    assert noise["duration_s"] == pytest.approx(RECORDING_S)
    white = noise["channels"]["gx"]["coefficients"]["white"]
    assert white["unit"] == "deg/sqrt(h)" and white["lo"] < white["value"] < white["hi"]
    assert doc["qa"]["status"] == "limits"  # the configured limit failed
    assert any("[noise]" in r for r in doc["qa"]["reasons"])


def test_the_lot_report_overlays_the_curves_with_the_flagged_unit_in_red(lot):
    html = lot["report"].read_text()
    start = html.index('<section id="noise">')
    section = html[start : html.index("</section>", start)]
    assert 'data-name="noise-allan-gyro"' in section and 'data-name="noise-allan-accel"' in section
    assert f"<b>{lot['noisy']}</b>" in section and "x the lot median" in section
    spec = json.loads(
        section.split('<script type="application/json" id="', 1)[1].split(">", 1)[1].split("</script>", 1)[0]
    )
    red = {t["meta"]["unit"] for t in spec["data"] if t["meta"]["flagged"]}
    grey = {t["meta"]["unit"] for t in spec["data"] if not t["meta"]["flagged"]}
    assert red == {lot["noisy"]} and len(grey) == 9
    # each unit's block has its noise part: the noisy unit's names its flags
    block = html[html.index(f'id="unit-{lot["noisy"]}"') :]
    block = block[: block.index("</details>")]
    assert "<h4>Noise</h4>" in block and "x the lot median" in block


@pytest.mark.browser
def test_the_noise_section_renders_in_chromium(lot):
    from reports.browser import Chromium, find_chromium

    if find_chromium() is None:
        pytest.skip("Debian's chromium is not installed (run tools/install-browser.sh)")
    with Chromium(width=1400, height=1000, timeout_s=120) as b:
        b.open(lot["report"])
        b.wait_figures()
        b.pump(0.3)
        facts = b.evaluate("""(function(){
            var figs = Array.from(document.querySelectorAll('#noise .figure'));
            return figs.map(function(f){
                var gd = f.querySelector('.js-plotly-plot') || f;
                var traces = (gd.data || []);
                return {state: f.getAttribute('data-state'),
                        paths: f.querySelectorAll('.scatterlayer .trace').length,
                        red: traces.filter(function(t){return t.meta && t.meta.flagged;}).map(
                            function(t){return t.meta.unit;}),
                        xtype: gd.layout ? gd.layout.xaxis.type : null};
            });
        })()""")
        assert b.log.errors == [] and b.log.external_requests == []
    assert len(facts) == 2 and all(f["state"] == "rendered" for f in facts), facts
    gyro = facts[0]
    assert gyro["paths"] == 30 and gyro["xtype"] == "log"  # 10 units x 3 channels
    assert set(gyro["red"]) == {lot["noisy"]}


MPU6050 = "../shared/data/real/mpu6050_tedaldi/example_data_tinit_calc.csv"


def test_simulate_noise_from_the_real_mpu6050_model(tmp_path):
    """``mimucal simulate --noise-from`` the real MPU-6050's measured model: the nightly's
    measurement of each simulated unit gives that model back (white within the unit's
    interval of the model's on most channels, the 38 Hz gyro-y line named with its
    amplitude)."""
    from pathlib import Path

    from flows.cli import main

    src = Path(__file__).resolve().parents[1] / MPU6050
    if not src.exists():
        pytest.skip(f"{MPU6050} is not there")
    noise_json = tmp_path / "mpu.json"
    args = ["noise", str(src), "--gyro-unit", "counts", "--accel-unit", "counts"]
    assert main([*args, "--gyro-range", "250dps", "--accel-range", "2g", "--json", str(noise_json)]) == 0
    model = json.loads(noise_json.read_text())
    line = model["channels"]["gy"]["periodic"][0]
    assert abs(line["frequency_hz"] - 38.0) < 0.1
    assert (
        main(
            [
                "simulate",
                str(tmp_path / "data"),
                "--units",
                "3",
                "--reps",
                "2",
                "--rate",
                "100",
                "--noise-recordings",
                "300",
                "--noise-from",
                str(noise_json),
                "--seed",
                "4",
            ]
        )
        == 0
    )
    refs, _ = find_sessions(tmp_path / "data")
    jobs, _, _ = plan_unit_jobs(refs, {})
    results = calibrate_batch(jobs, run_discovery=False)
    inside = []
    for r in results:
        doc = r.outcome.noise.model["channels"]
        for ch in ("gx", "gy", "gz", "ax", "ay", "az"):
            got = doc[ch]["coefficients"]["white"]
            want = model["channels"][ch]["coefficients"]["white"]["value"]
            assert got["value"] == pytest.approx(want, rel=0.05), (r.unit, ch)
            inside.append(got["lo"] <= want <= got["hi"])
        lines = [p for p in doc["gy"]["periodic"] if abs(p["frequency_hz"] - line["frequency_hz"]) < 0.1]
        assert len(lines) == 1 and lines[0]["amplitude"] == pytest.approx(line["amplitude"], rel=0.3), r.unit
    assert np.mean(inside) >= 0.75, inside
