"""The benchmark command runs end to end on a tiny fleet (2 units x 2 repetitions at 10 Hz).

Not a timed test: it only proves that ``python -m benchmarks.run`` simulates, scans, fits,
and writes its table and raw numbers. The real benchmark is ``make bench`` (BENCHMARKS.md).
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]


@pytest.mark.slow
def test_benchmark_harness_runs_on_a_tiny_fleet(tmp_path):
    out = tmp_path / "bench.md"
    work = tmp_path / "work"
    proc = subprocess.run(
        [
            sys.executable,
            "-m",
            "benchmarks.run",
            "--sizes",
            "2",
            "--rate",
            "10",
            "--reps",
            "2",
            "--no-nightly",
            "--only",
            "simulate,floor,fit_1proc",
            "--workdir",
            str(work),
            "--output",
            str(out),
        ],
        cwd=REPO,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert proc.returncode == 0, proc.stderr[-2000:]
    raw = json.loads(out.with_suffix(".json").read_text())
    r = raw["sizes"]["2"]
    n_steps = r["simulate"]["n_steps"]
    # 2 units x 2 reps were written, every file scanned, every session fitted
    assert r["simulate"]["sessions"] == 4
    assert r["floor"]["sessions"] == 4 and r["floor"]["steps"] == 4 * n_steps
    assert r["fit_1proc"]["units"] == 2
    assert r["fit_1proc"]["sessions_ok"] == 4 and r["fit_1proc"]["sessions_failed"] == 0
    for m in ("simulate", "floor", "fit_1proc"):
        assert r[m]["self_peak_rss_mb"] > 10  # the child's own ru_maxrss was read
    assert "fit_2proc" not in r  # --only skipped it
    text = out.read_text()
    assert text.startswith("# mimucal benchmarks")
    assert any(line.startswith("| 2 | 4 |") for line in text.splitlines())
    # the fleet is deleted after the run
    assert not (work / "fleet-2").exists()


def test_fit_vs_floor_verdict_is_the_issues_measure_and_shows_the_others():
    """The verdict judges the fit phase as issue 32 defines it (2 worker processes, wall,
    without the lot flags) against the floor; the flags, one process's CPU and the Prefect
    nightly stay in the measured text, so that a better figure cannot hide them
    (made-up measurements)."""
    sys.path.insert(0, str(REPO))
    from benchmarks.run import _fit_vs_floor_row

    r = {
        "fit_1proc": {
            "cpu_s": 20.0,
            "calibrate_cpu_s": 19.0,
            "floor_cpu_s": 10.0,
            "elapsed_s": 18.0,
            "floor_s": 8.0,
        },
        "fit_2proc": {"calibrate_s": 11.0, "elapsed_s": 12.0, "floor_s": 8.0},
        "nightly_processes": {"fit_phase_s": 24.0},
    }
    target, measured, verdict = _fit_vs_floor_row(r, 200)
    assert "200 units" in target and "2 processes, wall" in target
    assert verdict == "met"  # 11 / 8 = 1.375x <= 1.5x
    # the other ratios are shown: with the flags 1.50x, CPU 1.90x (2.00x with flags), Prefect 3.00x
    for shown in ("1.38x", "1.50x", "1.90x", "2.00x", "3.00x"):
        assert shown in measured
    r["fit_2proc"]["calibrate_s"] = 16.0
    assert _fit_vs_floor_row(r, 200)[2] == "missed by 1.33x"
    assert _fit_vs_floor_row(r, 1000)[2] == "missed by 1.33x"
    assert _fit_vs_floor_row(r, 45)[2] == "met"  # 2.0x at 45 units
    assert _fit_vs_floor_row({"fit_1proc": r["fit_1proc"]}, 50) is None
    assert _fit_vs_floor_row({}, 50) is None


def test_verdicts_state_the_cpu_bound_of_the_machines_cores():
    """Dask 2 vs 1 worker and the Prefect nightly's fit phase: the verdict's why gives the
    least time their measured CPU allows on the machine's cores (made-up measurements)."""
    sys.path.insert(0, str(REPO))
    from benchmarks.run import verdicts

    roles = {"api": 1.0, "flow": 1.0, "workers": 6.0, "writer": 2.0}  # 10 s of CPU
    size = {
        "fit_1proc": {"cpu_s": 8.0, "floor_cpu_s": 4.0, "elapsed_s": 7.0, "floor_s": 2.5},
        "fit_2proc": {"calibrate_s": 4.0, "elapsed_s": 4.2, "floor_s": 2.5},
        "nightly_processes": {"fit_phase_s": 5.5, "fit_phase_cpu_s": roles},
        "nightly_dask1": {
            "fit_phase_s": 6.0,
            "batch_size": 8,
            "fit_phase_cpu_s": {"workers": 5.5, "flow": 2.0},
        },
        "nightly_dask2": {
            "fit_phase_s": 5.5,
            "batch_size": 8,
            "dask_warmup_s": 1.0,
            "fit_phase_cpu_s": roles,
        },
    }
    doc = {
        "sizes": {"200": size},
        "config": {"batch": 8},
        "machine": {"nproc": 2, "load_start": (0.0, 0.0, 0.0)},
    }
    rows = {target: why for target, _, _, why in verdicts(doc)}
    # 10 s of CPU on 2 cores: at least 5.0 s, 2.00x a 2.5 s floor; 6.0 / 5.0 = 1.20x for Dask
    fit_why = rows[
        "fit phase (read, validate, average, fit, discovery, aggregate) <= 1.5x floor at 200 units, "
        "2 processes, wall"
    ]
    assert "on 2 cores at least 5.0 s: 2.00x the floor" in fit_why
    dask_why = rows["Dask 2 workers >= 1.6x 1 worker (200 units, fit phase)"]
    assert "takes at least 5.0 s, so 2 workers can at best reach 1.20x" in dask_why
