"""Regenerate the W_INCONSISTENT_STEP figures of docs/hardening.md ("a step that contradicts
its reference"): the largest robust z of clean units, and the catch rate of one sample damaged
inside the full scale.

    .venv/bin/python -m tools.step_consistency_figures [N_PROJECT [N_PHYSICS [N_CATCH]]]
        # defaults 1000 300 300, as in the doc (~10 min + ~9 min + ~1 min on a loaded 2-core machine)

Seeded: the same numbers every run. The units are those of tests/test_hardening_consistency.py
(project simulator with REALISTIC_NOISE; physics simulator with lever arms up to 12 mm,
nonlinearity, g-sensitivity, random walk and a tilted table axis).
"""

from __future__ import annotations

import sys
from dataclasses import replace
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))

REPS = (2, 3, 5)


def largest_z(make_unit, n_units: int, first_seed: int) -> dict[int, float]:
    """Largest |robust z| over every step, channel and repetition of ``n_units`` clean units."""
    from calib_core.guards import inconsistent_steps

    out = {}
    for reps in REPS:
        worst = 0.0
        for u in range(n_units):
            found = inconsistent_steps(make_unit(first_seed + u, reps), z_limit=0.0)
            worst = max([worst] + [abs(d.z) for d in found])
        out[reps] = worst
    return out


def catch_rate(n_units: int) -> dict[int, tuple[int, float]]:
    """One sample of a random step and channel replaced by a value uniform inside the full
    scale (the step mean moves by (value - mean) / count): how many are caught, and the
    largest step-mean shift (raw unit) of the missed ones."""
    from test_hardening_consistency import _project_unit

    from calib_core.guards import inconsistent_steps

    out = {}
    for reps in REPS:
        caught, missed = 0, 0.0
        for u in range(n_units):
            rng = np.random.default_rng(5000 + u)
            sms = _project_unit(5000 + u, reps)
            r, c = int(rng.integers(reps)), int(rng.integers(6))
            sm = sms[r]
            i = int(rng.integers(len(sm)))
            fs = (np.asarray(sm.gyro_range_dps) if c < 3 else np.asarray(sm.accel_range_g))[c % 3]
            values = (sm.gyro if c < 3 else sm.accel).copy()
            shift = (rng.uniform(-fs, fs) - values[i, c % 3]) / sm.count[i]
            values[i, c % 3] += shift
            sms[r] = replace(sm, **({"gyro": values} if c < 3 else {"accel": values}))
            hit = any(
                d.step == int(sm.step[i]) and (d.index == r or d.ambiguous) for d in inconsistent_steps(sms)
            )
            caught += hit
            if not hit:
                missed = max(missed, abs(shift))
        out[reps] = (caught, missed)
    return out


def main(n_project: int = 1000, n_physics: int = 300, n_catch: int = 300) -> None:
    from test_hardening_consistency import _physics_unit, _project_unit

    for name, make, n, seed in (
        ("project simulator", _project_unit, n_project, 1000),
        ("physics simulator", _physics_unit, n_physics, 1000),
    ):
        z = largest_z(make, n, seed)
        print(f"clean units, {name}, {n} units: largest robust z " + " / ".join(f"{z[r]:.1f}" for r in REPS))
    for reps, (caught, missed) in catch_rate(n_catch).items():
        print(
            f"{reps} reps: one sample damaged inside full scale: caught {caught}/{n_catch}; "
            f"largest missed shift {missed:.3g}"
        )


if __name__ == "__main__":
    main(*(int(a) for a in sys.argv[1:4]))
