"""Golden set of model discovery: record what :func:`calib_core.discovery.diagnose_unit` gives
on a fixed set of simulated units, and compare a later run with the record.

A refactor of the engine must give the same diagnoses bit for bit (or say which number moved,
by how much and why). The units cover the engine's paths: fast-simulator units with 3 and 5
repetitions, physics units clean and with each catalogue effect hidden, repetitions back to
back on one warm-up (the between-repetition test), a unit whose repetitions have different
steps (the unbalanced grid), and the static engine on the real recordings' poses.

Usage::

    python -m tools.discovery_golden record OUT.pkl [--sessions CACHE.pkl]
    python -m tools.discovery_golden compare A.pkl B.pkl
    python -m tools.discovery_golden profile [--sessions CACHE.pkl] [--units N]

The simulated sessions are kept in ``--sessions`` (simulating the physics units costs more
than diagnosing them); ``record`` runs every unit once and keeps per unit the diagnosis's
``to_dict()``, every calibration's arrays, the replayed residual tables and the evidence
series, with the CPU time per unit.
"""

from __future__ import annotations

import argparse
import pickle
import sys
import time
from pathlib import Path

import numpy as np
import pandas as pd

EFFECTS = (
    "accel_scale_nonlinearity",
    "gyro_g_sensitivity",
    "gyro_scale_asymmetry",
    "gyro_scale_nonlinearity",
    "lever_arm",
    "thermal_bias_drift",
    "thermal_scale_drift",
)


def simulate() -> dict[str, list]:
    """The golden set's sessions, by name."""
    from calib_core.effects import get_effect
    from calib_core.sim import protocols
    from calib_core.sim import simulator as sim
    from calib_core.sim.physics import Turntable, typical_physics_unit
    from calib_core.sim.simulator import REALISTIC_NOISE, simulate_unit
    from schemas.physics_sessions import physics_unit_step_means

    steps = protocols.default_session()
    out: dict[str, list] = {}
    for seed, reps in ((1, 3), (2, 5), (3, 5), (4, 4)):
        rng = np.random.default_rng(seed)
        truth = sim.typical_truth(rng, **REALISTIC_NOISE)
        out[f"fast-{seed}-r{reps}"], _ = simulate_unit(truth, steps, rng, reps, unit=f"F{seed}")
    # unbalanced: one repetition misses two steps
    s = out["fast-3-r5"]
    keep = np.ones(len(s[1]), bool)
    keep[[5, 50]] = False
    out["fast-3-unbalanced"] = [s[0], s[1].select(keep)] + list(s[2:])
    rng = np.random.default_rng(2026)
    for k in range(3):
        unit = typical_physics_unit(rng)
        out[f"physics-clean-{k}"] = physics_unit_step_means(unit, steps, rng, n_reps=5, unit_id=f"C{k}")
    for name in EFFECTS:
        unit = typical_physics_unit(rng)
        unit, theta, _ = get_effect(name).hide(unit, rng, 1.0)
        table = get_effect(name).table_knobs(theta)
        out[f"physics-{name}"] = physics_unit_step_means(
            unit, steps, rng, n_reps=5, unit_id=f"H{len(out)}", table=Turntable(**table)
        )
    for k, name in enumerate(("", "thermal_scale_drift")):
        unit = typical_physics_unit(rng)
        if name:
            unit, _, _ = get_effect(name).hide(unit, rng, 1.0)
        out[f"physics-back-to-back-{name or 'clean'}"] = physics_unit_step_means(
            unit, steps, rng, n_reps=5, unit_id=f"B{k}", table=Turntable(), back_to_back=True
        )
    return out


def sessions(cache: Path | None) -> dict[str, list]:
    if cache is not None and cache.exists():
        return pickle.loads(cache.read_bytes())
    out = simulate()
    if cache is not None:
        cache.write_bytes(pickle.dumps(out))
    return out


def _cal(c) -> dict:
    return {
        "K_g": c.K_g,
        "w0": c.w0,
        "K_a": c.K_a,
        "f0": c.f0,
        "terms": [
            (t.name, np.asarray(t.params), np.asarray(t.stderr), dict(t.undetermined)) for t in c.terms
        ],
    }


def record_one(sess: list) -> dict:
    from calib_core.discovery import diagnose_unit

    t0 = time.process_time()
    d = diagnose_unit(sess, alpha=0.01, tables=True)
    cpu = time.process_time() - t0
    return {
        "dict": d.to_dict(),
        "before": [_cal(c) for c in d.calibrations_before],
        "after": [_cal(c) for c in d.calibrations_after],
        "residuals_before": d.residuals_before,
        "residuals_after": d.residuals_after,
        "evidence": d.evidence,
        "cpu_s": cpu,
    }


def static_golden() -> dict:
    """The static engine on the real recordings' poses (when the shared data are there):
    the calibration and the pose table are kept with the result, so that a later run
    diagnoses the same inputs."""
    from calib_core.discovery import diagnose_static
    from flows.commands.diagnose_real import DEFAULT_DATA, load_recording

    out = {}
    for which, block in (("xsens", 4), ("ferraris", 1)):
        try:
            cal, poses, label = load_recording(which, DEFAULT_DATA)
        except Exception as exc:  # the shared data absent: the turntable set alone
            print(f"static {which} skipped: {exc}", file=sys.stderr)
            continue
        t0 = time.process_time()
        d = diagnose_static(cal, poses, label, block_size=block)
        out[f"static-{which}"] = {"dict": d.to_dict(), "static_cpu_s": time.process_time() - t0}
    return out


def record(out: Path, cache: Path | None) -> None:
    res = {name: record_one(s) for name, s in sessions(cache).items()}
    res.update(static_golden())
    out.write_bytes(pickle.dumps(res))
    cpu = [r["cpu_s"] for r in res.values() if "cpu_s" in r]
    print(f"{len(res)} units recorded; discovery CPU {1e3 * np.mean(cpu):.1f} ms/unit (mean), tables on")


def _diff(a, b, path: str, out: list[str]) -> None:
    if isinstance(a, dict):
        if set(a) != set(b):
            out.append(f"{path}: keys {sorted(set(a) ^ set(b))}")
        for k in a:
            if k in b:
                _diff(a[k], b[k], f"{path}.{k}", out)
    elif isinstance(a, (list, tuple)):
        if len(a) != len(b):
            out.append(f"{path}: length {len(a)} != {len(b)}")
        for i, (x, y) in enumerate(zip(a, b)):
            _diff(x, y, f"{path}[{i}]", out)
    elif isinstance(a, pd.DataFrame):
        if list(a.columns) != list(b.columns) or len(a) != len(b):
            out.append(f"{path}: frame shape/columns differ")
            return
        for col in a.columns:
            _diff(a[col].to_numpy(), b[col].to_numpy(), f"{path}[{col}]", out)
    elif isinstance(a, np.ndarray) or isinstance(a, float):
        a, b = np.asarray(a), np.asarray(b)
        if a.shape != b.shape:
            out.append(f"{path}: shape {a.shape} != {b.shape}")
        elif a.dtype.kind in "fc":
            if not np.array_equal(a, b, equal_nan=True):
                fin = np.isfinite(a) & np.isfinite(b)
                rel = np.max(np.abs(a - b)[fin] / np.maximum(np.abs(a[fin]), 1e-300), initial=0.0)
                same_nan = np.array_equal(np.isnan(a), np.isnan(b))
                out.append(f"{path}: max rel diff {rel:.3g}{'' if same_nan else ' (NaN pattern differs)'}")
        elif not np.array_equal(a, b):
            out.append(f"{path}: differs")
    elif a != b:
        out.append(f"{path}: {a!r} != {b!r}")


def compare(a: Path, b: Path) -> int:
    A, B = pickle.loads(a.read_bytes()), pickle.loads(b.read_bytes())
    diffs: list[str] = []
    for name in A:
        if name not in B:
            diffs.append(f"{name}: missing")
            continue
        x = {k: v for k, v in A[name].items() if not k.endswith("cpu_s")}
        y = {k: v for k, v in B[name].items() if not k.endswith("cpu_s")}
        _diff(x, y, name, diffs)
    cpu = [np.mean([r["cpu_s"] for r in R.values() if "cpu_s" in r]) for R in (A, B)]
    print(f"CPU per unit: {1e3 * cpu[0]:.1f} ms -> {1e3 * cpu[1]:.1f} ms (tables on; machine load applies)")
    print("\n".join(diffs[:200]) if diffs else f"identical: {len(A)} units, every number bit for bit")
    return 1 if diffs else 0


def profile(cache: Path | None, n_units: int) -> None:
    import cProfile
    import pstats

    from calib_core.discovery import diagnose_unit

    units = list(sessions(cache).values())
    units = (units * (1 + n_units // len(units)))[:n_units]
    diagnose_unit(units[0], tables=False)  # first-call costs out of the profile
    pr = cProfile.Profile()
    t0 = time.process_time()
    pr.enable()
    for s in units:
        diagnose_unit(s, tables=False)
    pr.disable()
    cpu = time.process_time() - t0
    print(f"{n_units} units, tables off: {1e3 * cpu / n_units:.1f} ms CPU/unit under the profiler")
    pstats.Stats(pr).sort_stats("tottime").print_stats(35)
    pstats.Stats(pr).sort_stats("cumulative").print_stats(45)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = p.add_subparsers(dest="cmd", required=True)
    r = sub.add_parser("record")
    r.add_argument("out", type=Path)
    r.add_argument("--sessions", type=Path)
    c = sub.add_parser("compare")
    c.add_argument("a", type=Path)
    c.add_argument("b", type=Path)
    f = sub.add_parser("profile")
    f.add_argument("--sessions", type=Path)
    f.add_argument("--units", type=int, default=20)
    a = p.parse_args(argv)
    if a.cmd == "record":
        record(a.out, a.sessions)
    elif a.cmd == "compare":
        return compare(a.a, a.b)
    else:
        profile(a.sessions, a.units)
    return 0


if __name__ == "__main__":
    sys.exit(main())
