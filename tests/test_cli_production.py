"""Production use through the CLI (issue 20 items 5 and 8): one calibration file format from
`calibrate --json` to `apply`, a short `calibrate` summary, closed pipes, `apply` writing the
format its output name says, user errors answered before Prefect starts with what exists,
clean help texts, Prefect's logs in a file, per-lot progress lines, true wall times."""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pandas as pd
import pyarrow.parquet as pq
import pytest

from flows.fleet_sim import simulate_fleet

from conftest import load_manifest

ROOT = Path(__file__).resolve().parent.parent
# a user's shell: none of the PREFECT_* settings that modules imported by other tests of this
# process put into os.environ (flows.nightly sets Prefect's defaults when imported)
ENV = {**{k: v for k, v in os.environ.items() if not k.startswith("PREFECT_")}, "PYTHONPATH": str(ROOT)}


def mimucal(*args: str, **kw) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", "flows.cli", *map(str, args)],
        capture_output=True,
        text=True,
        env=ENV,
        timeout=300,
        **kw,
    )


@pytest.fixture(scope="module")
def data(tmp_path_factory):
    """One lot, two units, three repetitions at 10 Hz; U0002's rep 2 is damaged."""
    base = tmp_path_factory.mktemp("prod")
    root = base / "data"
    simulate_fleet(root, lots=1, units=2, reps=3, seed=11, sample_rate_hz=10.0)
    # a NaN burst in one session of U0002 (the reader refuses it with E_NONFINITE_VALUE)
    path = root / "lot=L01" / "unit=U0002" / "rep=2" / "samples.parquet"
    t = pq.read_table(path)
    df = t.to_pandas()
    df.loc[100:120, "gx"] = np.nan
    import pyarrow as pa

    pq.write_table(
        pa.Table.from_pandas(df, preserve_index=False).replace_schema_metadata(t.schema.metadata), path
    )
    return base, root


def test_calibrate_json_is_the_file_apply_reads_and_the_summary_is_short(data):
    base, root = data
    cal_path = base / "U0001.json"
    out = mimucal("calibrate", root, "--unit", "U0001", "--json", cal_path)
    assert out.returncode == 0, out.stderr
    lines = out.stdout.splitlines()
    assert 6 <= len(lines) <= 14, out.stdout
    assert lines[0] == "unit U0001 (lot L01): 3 repetition(s) calibrated, 0 failed"
    scale = next(x for x in lines if x.startswith("gyro scale"))
    assert re.search(r"\(spread [\d.]+ ppm +[\d.]+ ppm +[\d.]+ ppm\)$", scale), scale
    bias = next(x for x in lines if x.startswith("gyro bias"))
    assert "deg/h" in bias and "deg/s" in bias
    assert "mg" in next(x for x in lines if x.startswith("accel bias"))
    # the file is the store's format, with its version, and its per-repetition section
    doc = json.loads(cal_path.read_text())
    assert doc["format"] == "mimucal-calibration" and doc["format_version"] == "1.0"
    assert [r["rep"] for r in doc["repetitions"]] == [1, 2, 3]
    assert doc["provenance"]["unit"] == "U0001" and set(doc["averaged"]) == {"mean", "std", "units"}
    # the averaged K_g is the mean of the repetitions' (the calibration applied: no term kept)
    kg = np.mean([r["K_g"] for r in doc["repetitions"]], axis=0)
    if not doc["terms"] or all(t["name"] == "lever_arm" for t in doc["terms"]):
        assert np.allclose(doc["K_g"], kg, atol=1e-12)
    # the truth is known: the K_g recovered to 1e-3
    truth = next(u for u in load_manifest(root)["units"] if u["unit"] == "U0001")["truth"]
    assert np.abs(np.array(doc["K_g"]) - np.array(truth["K_g"])).max() < 1e-3
    # apply reads it: the CSV and Parquet outputs hold the same numbers
    raw = root / "lot=L01" / "unit=U0001" / "rep=1" / "samples.parquet"
    a = mimucal("apply", cal_path, raw, base / "cal.parquet")
    b = mimucal("apply", cal_path, raw, base / "cal.csv")
    assert a.returncode == 0 and b.returncode == 0, a.stderr + b.stderr
    assert pq.ParquetFile(base / "cal.parquet").metadata.num_rows > 0
    with open(base / "cal.csv", "rb") as fh:
        assert not fh.read(4).startswith(b"PAR1")  # a CSV, not Parquet under a .csv name
    p = pd.read_parquet(base / "cal.parquet")
    c = pd.read_csv(base / "cal.csv")
    assert list(c.columns) == list(p.columns)
    assert np.allclose(c[["w_x", "f_z"]].to_numpy(), p[["w_x", "f_z"]].to_numpy(), rtol=1e-12)
    bad = mimucal("apply", cal_path, raw, base / "cal.txt")
    assert bad.returncode == 2 and not (base / "cal.txt").exists()
    assert bad.stderr.strip().count("\n") == 0 and ".parquet or .csv" in bad.stderr


def test_calibrate_full_prints_the_file_and_a_failed_session_is_one_line(data):
    base, root = data
    out = mimucal("calibrate", root, "--unit", "U0002", "--full", "--no-discovery")
    assert out.returncode == 1  # a session failed
    doc = json.loads(out.stdout)
    assert doc["format"] == "mimucal-calibration"
    assert [r["rep"] for r in doc["repetitions"]] == [1, 3]
    assert doc["provenance"]["sessions_failed"][0]["code"] == "E_NONFINITE_VALUE"
    short = mimucal("calibrate", root, "--unit", "U0002", "--no-discovery")
    failed = [x for x in short.stdout.splitlines() if x.startswith("failed rep 2")]
    assert len(failed) == 1 and "E_NONFINITE_VALUE" in failed[0]


@pytest.mark.parametrize(
    "args",
    [
        ("calibrate", "{root}", "--unit", "U0001", "--full", "--no-discovery"),
        ("simulate", "{base}/sim", "--lots", "1", "--units", "1", "--reps", "1", "--rate", "5"),
        ("--help",),
    ],
)
def test_a_closed_pipe_ends_quietly(data, args):
    """The reader goes away before the command writes (as `| head` does): no traceback,
    the exit code of a command its pipe ended (141, as `seq`)."""
    base, root = data
    argv = [a.format(root=root, base=base) for a in args]
    proc = subprocess.Popen(
        [sys.executable, "-m", "flows.cli", *argv], stdout=subprocess.PIPE, stderr=subprocess.PIPE, env=ENV
    )
    proc.stdout.close()  # the reader is gone
    err = proc.stderr.read().decode()
    rc = proc.wait(timeout=300)
    assert "Traceback" not in err and "BrokenPipeError" not in err, err
    # argparse drops a help text it cannot write (exit 0); the commands' output ends in 141
    assert rc == (0 if argv == ["--help"] else 141)


def test_every_help_text_renders_without_rest_markup():
    from flows.cli import build_parser

    parser = build_parser()
    sub = next(a for a in parser._actions if a.dest == "command")
    seen = 0
    for name, p in sub.choices.items():
        text = p.format_help()
        assert "``" not in text, f"{name} --help shows raw reST literals"
        seen += 1
    assert seen >= 14


@pytest.fixture(scope="module")
def store(tmp_path_factory):
    """A results store with two lots (units table only: enough for the checks that answer
    before Prefect starts)."""
    from schemas.results_store import ResultsStore

    root = tmp_path_factory.mktemp("store") / "results"
    st = ResultsStore(root)
    st.write(
        "units",
        pd.DataFrame(
            [
                {
                    "lot": lot,
                    "unit": unit,
                    "n_sessions": 1,
                    "n_ok": 1,
                    "n_warned": 0,
                    "n_failed": 0,
                    "run_id": "r",
                    "updated_at": "2026-11-20T00:00:00Z",
                    "state": "calibrated",
                    "reason": "",
                    "calibration_file": None,
                    "calibrated_at": None,
                }
                for lot, unit in (("L01", "U0001"), ("L01", "U0002"), ("L02", "U0003"))
            ]
        ),
    )
    return root


@pytest.mark.slow
def test_a_wrong_lot_or_unit_is_one_line_with_what_exists_before_prefect(data, store):
    base, root = data
    t0 = time.monotonic()
    r = mimucal("report", "--results", store, "--lot", "L9")
    took = time.monotonic() - t0
    assert r.returncode == 2
    assert r.stderr.strip() == (
        f"mimucal report: error: lot 'L9' is not in results store {store} (lots: L01, L02)"
    )
    assert took < 5.0  # no Prefect start-up (8.6 s before)
    assert not (store / ".prefect").exists()
    r = mimucal("rerun", root, "--results", store, "--unit", "U9")
    assert r.returncode == 2
    assert r.stderr.strip() == (
        f"mimucal rerun: error: unit 'U9' is not in dataset {root} (units: U0001, U0002)"
    )
    r = mimucal("report", "--results", base / "nowhere", "--lot", "L01")
    assert r.returncode == 2 and r.stderr.count("\n") == 1 and "run 'mimucal nightly'" in r.stderr
    r = mimucal("calibrate", root, "--unit", "U7")
    assert r.returncode == 2 and "(units: U0001, U0002)" in r.stderr and r.stderr.count("\n") == 1
    r = mimucal("diagnose", root, "--unit", "U7")
    assert r.returncode == 2 and "(units: U0001, U0002)" in r.stderr and r.stderr.count("\n") == 1
    r = mimucal("calibration", "--results", store, "--unit", "U7")
    assert r.returncode == 2 and r.stderr.count("\n") == 1
    assert "(units with calibrations: none)" in r.stderr


def test_report_pdf_without_chromium_is_one_clear_line_before_the_run(store):
    env = {**ENV, "MIMUCAL_CHROMIUM": "/nonexistent/chromium"}
    t0 = time.monotonic()
    r = subprocess.run(
        [sys.executable, "-m", "flows.cli", "report", "--results", str(store), "--lot", "L01", "--pdf"],
        capture_output=True,
        text=True,
        env=env,
        timeout=120,
    )
    assert r.returncode == 2 and time.monotonic() - t0 < 5.0
    assert r.stderr.count("\n") == 1 and "needs Debian's chromium" in r.stderr
    assert "apt-get install chromium" in r.stderr


@pytest.mark.slow
def test_nightly_logs_prefect_to_a_file_prints_progress_and_wall_time(data):
    """Prefect's INFO lines go to RESULTS/logs/prefect.log; the terminal has the per-lot
    progress lines and the summary with the command's wall time (--verbose: Prefect's lines
    on the terminal too)."""
    base, root = data
    results = base / "results"
    t0 = time.monotonic()
    r = mimucal(
        "nightly",
        root,
        "--results",
        results,
        "--no-discovery",
        "--batch-size",
        "1",
        "--runner",
        "threads",
        "--unit-reports",
    )
    wall = time.monotonic() - t0
    assert r.returncode == 1, r.stderr  # exit code 1: the dataset's bad session failed
    assert " | INFO " not in r.stderr and "Flow run" not in r.stderr, r.stderr
    log = (results / "logs" / "prefect.log").read_text()
    assert "Flow run" in log and "Finished in state Completed" in log
    progress = re.findall(r"^lot L01: (\d)/2 units(?: \((\d) failed sessions\))?, [\d.]+ s$", r.stderr, re.M)
    assert [int(n) for n, _ in progress] == [1, 2], r.stderr
    m = re.search(r"; ([\d.]+) s wall \(([\d.]+) s in the flow\)$", r.stdout, re.M)
    assert m, r.stdout
    reported, in_flow = float(m.group(1)), float(m.group(2))
    assert in_flow < reported <= wall + 0.1 and reported > 0.8 * wall
    # --unit-reports (the demo's): a report per unit of the lot
    assert sorted(p.name for p in (results / "reports" / "units").glob("*.html")) == [
        "U0001.html",
        "U0002.html",
    ]
    assert "unit reports: " in r.stdout
    from reports.browser import find_chromium

    if find_chromium() is not None:  # the lot report printed to PDF through the CLI
        pdf = mimucal("report", "--results", results, "--lot", "L01", "--pdf", base / "L01.pdf")
        assert pdf.returncode == 0, pdf.stderr
        assert pdf.stdout.splitlines()[-1] == str(base / "L01.pdf")
        assert (base / "L01.pdf").read_bytes()[:5] == b"%PDF-"


@pytest.mark.parametrize("verbose", [False, True])
def test_verbose_leaves_prefect_logging_on_the_terminal(tmp_path, verbose):
    """ensure_environment routes Prefect's console handler to RESULTS/logs/prefect.log, or
    (verbose) leaves it on stderr at INFO; checked with Prefect's own logging set-up."""
    code = (
        "import logging, sys\n"
        "from flows import runtime\n"
        f"runtime.ensure_environment({str(tmp_path / 'results')!r}, verbose={verbose})\n"
        "import prefect\n"
        "from prefect.logging.configuration import setup_logging\n"
        "setup_logging()\n"
        "logging.getLogger('prefect.flow_runs').info('a flow run line')\n"
        "logging.getLogger('prefect').info('a prefect line')\n"
        "for h in logging.getLogger().handlers: h.flush()\n"
    )
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=ENV, timeout=300)
    assert r.returncode == 0, r.stderr
    log = tmp_path / "results" / "logs" / "prefect.log"
    if verbose:
        assert "a prefect line" in r.stderr and not log.exists()
    else:
        assert "a prefect line" not in r.stderr and "a prefect line" in log.read_text()
