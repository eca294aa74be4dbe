"""Coverage and false alarms of the measured-noise analysis (docs/noise.md).

    .venv/bin/python -m tools.noise_coverage [N_RECORDINGS [N_SAMPLES]]   # 200, 100000

Simulates N_RECORDINGS static single-channel recordings (100 Hz, N_SAMPLES each) from five
scenarios with known coefficients (gyro and accelerometer, with and without random walk,
quantization, an MPU-6050-like 38 Hz line), analyses each with
:func:`calib_core.noise.analyse_recording`, and prints per scenario and coefficient how often
the 95 % interval covers the truth (a process discovery does not name has the interval
[0, upper bound]), how often each process is named, how often a periodic line is named where
there is none, and the share of cluster sizes where the fitted model's Allan deviation lies
inside the measured 95 % intervals. Seeded: the same numbers every run.
"""

from __future__ import annotations

import sys
import time

import numpy as np

from calib_core.noise import ChannelNoise, NoiseModel, analyse_recording, synthesize
from calib_core.noise.model import COEFFICIENTS

RATE_HZ = 100.0
SCENARIOS = {
    "gyro white + bias instability": ChannelNoise("deg/s", {"white": 0.01, "bias_instability": 0.003}),
    "gyro + random walk": ChannelNoise(
        "deg/s", {"white": 0.01, "bias_instability": 0.002, "random_walk": 2e-3}
    ),
    "gyro + quantization": ChannelNoise(
        "deg/s", {"white": 0.01, "bias_instability": 0.002, "quantization": 2e-3}
    ),
    "accel + random walk": ChannelNoise("g", {"white": 1e-4, "bias_instability": 3e-5, "random_walk": 5e-5}),
    "MPU-6050-like gyro with a 38 Hz line": ChannelNoise(
        "deg/s",
        {"white": 0.011, "bias_instability": 0.0027},
        periodic=((37.99, 0.017),),
        resolution=250.0 / 32768.0,
    ),
}


def covers(noise: ChannelNoise, process: str, truth: float) -> bool:
    if process in noise.coefficients:
        lo, hi = noise.intervals[process]
    else:
        lo, hi = 0.0, noise.upper_bounds.get(process, np.inf)
    return bool(lo <= truth <= hi)


def evaluate(n_recordings: int = 200, n_samples: int = 100_000, seed: int = 31) -> dict:
    """{scenario: {"coverage": {process: share}, "named": {process: share}, "lines": share
    of recordings with a line named, "within_ci": mean share of cluster sizes, "n": count}}."""
    rng = np.random.default_rng(seed)
    names = list(SCENARIOS)
    acc: dict = {s: {"coverage": {}, "named": {}, "lines": [], "line_ok": [], "within_ci": []} for s in names}
    for i in range(n_recordings):
        scenario = names[i % len(names)]
        truth = SCENARIOS[scenario]
        model = NoiseModel(RATE_HZ, n_samples / RATE_HZ, {"x": truth})
        x = synthesize(model, n_samples, RATE_HZ, rng)["x"]
        ch = analyse_recording({"x": x}, RATE_HZ, {"x": truth.unit}).channels["x"]
        a = acc[scenario]
        for p in COEFFICIENTS:
            a["coverage"].setdefault(p, []).append(covers(ch.noise, p, truth.value(p)))
            a["named"].setdefault(p, []).append(p in ch.noise.coefficients)
        a["lines"].append(len(ch.noise.periodic) > 0)
        a["line_ok"].append(
            all(any(abs(f - tf) < 0.1 for f, _ in ch.noise.periodic) for tf, _ in truth.periodic)
        )
        a["within_ci"].append(ch.fit.fraction_within_ci)
        a["named"].setdefault("gauss_markov", []).append(ch.noise.gauss_markov is not None)
    out = {}
    for s, a in acc.items():
        out[s] = {
            "n": len(a["lines"]),
            "coverage": {p: float(np.mean(v)) for p, v in a["coverage"].items()},
            "named": {p: float(np.mean(v)) for p, v in a["named"].items()},
            "lines": float(np.mean(a["lines"])),
            "line_found": float(np.mean(a["line_ok"])),
            "within_ci": float(np.mean(a["within_ci"])),
        }
    return out


def pooled_coverage(result: dict) -> dict:
    """{(process, truth present): (share covered, recordings)} over the scenarios."""
    out = {}
    for p in COEFFICIENTS:
        for present in (True, False):
            rows = [r for s, r in result.items() if (SCENARIOS[s].value(p) > 0) == present]
            n = sum(r["n"] for r in rows)
            if n:
                out[(p, present)] = (sum(r["coverage"][p] * r["n"] for r in rows) / n, n)
    return out


def main(n_recordings: int = 200, n_samples: int = 100_000) -> None:
    t0 = time.perf_counter()
    result = evaluate(n_recordings, n_samples)
    print(f"{n_recordings} recordings of {n_samples} samples at {RATE_HZ:g} Hz")
    print(
        "| scenario | n | "
        + " | ".join(f"{p} cover (named)" for p in COEFFICIENTS)
        + " | Gauss-Markov named | line named | ADEV in CI |"
    )
    print("|---" * (len(COEFFICIENTS) + 5) + "|")
    for s, r in result.items():
        cells = [f"{r['coverage'][p]:.0%} ({r['named'][p]:.0%})" for p in COEFFICIENTS]
        print(
            f"| {s} | {r['n']} | "
            + " | ".join(cells)
            + f" | {r['named']['gauss_markov']:.0%} | {r['lines']:.0%} | {r['within_ci']:.0%} |"
        )
    parts = [
        f"{p} ({'true > 0' if present else 'true = 0'}) {share:.1%} of {n}"
        for (p, present), (share, n) in pooled_coverage(result).items()
    ]
    print("pooled coverage: " + "; ".join(parts))
    free = [r for s, r in result.items() if not SCENARIOS[s].periodic]
    fa = sum(r["lines"] * r["n"] for r in free) / sum(r["n"] for r in free)
    print(f"line-free recordings with a line named: {fa:.1%} of {sum(r['n'] for r in free)}")
    print(f"({time.perf_counter() - t0:.0f} s)")


if __name__ == "__main__":
    main(*(int(a) for a in sys.argv[1:3]))
