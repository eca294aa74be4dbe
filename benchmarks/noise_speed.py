"""Speed of the noise analysis (docs/noise.md, docs/benchmarks.md): Allan deviation, fit and
discovery of a 1e6-sample, 6-channel static recording (2.8 h at 100 Hz). Target: under 2 s.

    .venv/bin/python -m benchmarks.noise_speed [N_SAMPLES] [REPEATS]     # 1000000, 3

The recording is simulated from an MPU-6050-like model (white, bias instability and a random
walk on every channel, a 38 Hz line on the gyros; seeded) before the clock starts. Prints the
best of REPEATS analyses in wall and CPU time (this process), the split by stage for one
channel, and the load average (a load above the core count means other work shared the
machine: the CPU time is then the figure to compare).
"""

from __future__ import annotations

import os
import sys
import time

import numpy as np

from calib_core.noise import ChannelNoise, NoiseModel, analyse_recording, synthesize

RATE_HZ = 100.0
TARGET_S = 2.0


def recording(n: int) -> tuple[dict[str, np.ndarray], dict[str, str]]:
    gyro = ChannelNoise(
        "deg/s",
        {"white": 0.011, "bias_instability": 0.0027, "random_walk": 2e-4},
        periodic=((37.99, 0.017),),
    )
    accel = ChannelNoise("g", {"white": 6e-5, "bias_instability": 2e-5, "random_walk": 5e-6})
    chans = {c: (gyro if c[0] == "g" else accel) for c in ("gx", "gy", "gz", "ax", "ay", "az")}
    model = NoiseModel(RATE_HZ, n / RATE_HZ, chans)
    return synthesize(model, n, RATE_HZ, np.random.default_rng(2026)), {c: m.unit for c, m in chans.items()}


def stages(x: np.ndarray) -> dict[str, float]:
    """CPU seconds of each stage of one channel's analysis."""
    from calib_core.noise.allan import allan_curve
    from calib_core.noise.analysis import discover_terms, find_lines
    from calib_core.noise.fit import Line, fit_allan

    out = {}
    t = time.process_time()
    spectral = find_lines(x, RATE_HZ)
    out["periodic lines (Welch, both halves)"] = time.process_time() - t
    t = time.process_time()
    curve = allan_curve(x, RATE_HZ)
    out["Allan deviation, whole record (noise ID, edf)"] = time.process_time() - t
    t = time.process_time()
    h = x.size // 2
    halves = (
        allan_curve(x[:h], RATE_HZ, curve.m, curve.alpha),
        allan_curve(x[h:], RATE_HZ, curve.m, curve.alpha),
    )
    out["Allan deviation, halves"] = time.process_time() - t
    lines = tuple(Line(s.frequency_hz, s.amplitude) for s in spectral)
    t = time.process_time()
    terms, _ = discover_terms(halves, lines, x.size / RATE_HZ)
    out["discovery (fits on the halves)"] = time.process_time() - t
    t = time.process_time()
    fit_allan(curve, terms, lines)
    out["final fit"] = time.process_time() - t
    return out


def main(n: int = 1_000_000, repeats: int = 3) -> None:
    channels, units = recording(n)
    analyse_recording({k: v[:5000] for k, v in channels.items()}, RATE_HZ, units)  # warm caches
    load0 = os.getloadavg()
    walls, cpus = [], []
    for _ in range(repeats):
        w, c = time.perf_counter(), time.process_time()
        analyse_recording(channels, RATE_HZ, units)
        walls.append(time.perf_counter() - w)
        cpus.append(time.process_time() - c)
    load1 = os.getloadavg()
    print(f"noise analysis of {n:,} samples x 6 channels at {RATE_HZ:g} Hz ({n / RATE_HZ / 3600:.1f} h)")
    print(f"best of {repeats}: wall {min(walls):.2f} s, CPU {min(cpus):.2f} s (target < {TARGET_S:g} s)")
    wall_runs, cpu_runs = (", ".join(f"{v:.2f}" for v in runs) for runs in (walls, cpus))
    print(f"all runs: wall {wall_runs} s; CPU {cpu_runs} s")
    print(f"load average at start {load0[0]:.1f}, at end {load1[0]:.1f} ({os.cpu_count()} cores)")
    print("one gyro channel, CPU by stage (one BLAS thread, as analyse_recording runs):")
    from threadpoolctl import threadpool_limits

    with threadpool_limits(1):
        split = stages(channels["gy"])
    for name, sec in split.items():
        print(f"  {name}: {sec * 1000:.0f} ms")


if __name__ == "__main__":
    main(*(int(a) for a in sys.argv[1:3]))
