"""The benchmark command runs end to end on a tiny fleet (2 units x 2 repetitions at 10 Hz).

Not a timed test: it only proves that ``python -m benchmarks.run`` simulates, scans, fits,
and writes its table and raw numbers. The real benchmark is ``make bench`` (BENCHMARKS.md).
"""
from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


def test_benchmark_harness_runs_on_a_tiny_fleet(tmp_path):
    out = tmp_path / "bench.md"
    work = tmp_path / "work"
    proc = subprocess.run(
        [sys.executable, "-m", "benchmarks.run", "--sizes", "2", "--rate", "10", "--reps", "2",
         "--no-nightly", "--only", "simulate,floor,fit_1proc", "--workdir", str(work),
         "--output", str(out)],
        cwd=REPO, capture_output=True, text=True, timeout=120)
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
