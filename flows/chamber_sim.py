"""Chamber runs of the physics simulator through the real contract path: each session's
samples carry the metadata ``chamber_setpoint_c`` (and ``chamber_sweep``), and are either
averaged by the reader's own code (step means for the estimator, in memory) or written as
Parquet (``mimucal simulate --physics --chamber``).

The units, the schedule and the truth are :mod:`calib_core.sim.chamber`; the fit is
:mod:`calib_core.models.thermal`.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd

from calib_core.models.thermal import ChamberSessionInput
from calib_core.sim.chamber import ChamberSession, chamber_schedule, chamber_steps, with_soak
from calib_core.sim.physics import ChamberSoak, PhysicsUnit, simulate_physics_session
from calib_core.steps import SessionKey, StepMeans
from schemas.averaging import step_means_from_tables
from schemas.writer import write_session

T0 = pd.Timestamp("2026-11-01T00:00:00Z")
SESSION_SPACING_S = 7200.0  # one setpoint every two hours (soak + run)


def session_metadata(md: dict[str, str], session: ChamberSession, unit_id: str) -> dict[str, str]:
    start = (T0 + pd.Timedelta(seconds=SESSION_SPACING_S * session.order)).strftime("%Y-%m-%dT%H:%M:%SZ")
    return {
        **md,
        "session_start": start,
        "chamber_setpoint_c": f"{session.setpoint_c:g}",
        "chamber_sweep": session.sweep,
    }


def chamber_sessions(
    unit: PhysicsUnit,
    rng: np.random.Generator,
    schedule: list[ChamberSession] | None = None,
    steps: pd.DataFrame | None = None,
    rate_hz: float = 50.0,
    unit_id: str = "U000",
):
    """(session, samples, metadata) of every session of the schedule (default: 7 setpoints,
    2 sweeps), numbered rep = acquisition order + 1."""
    schedule = schedule if schedule is not None else chamber_schedule()
    steps = steps if steps is not None else chamber_steps()
    for s in schedule:
        samples, md = simulate_physics_session(with_soak(unit, s.soak), steps, rng, rate_hz=rate_hz)
        yield s, samples, session_metadata(md, s, unit_id)


def chamber_step_means(
    unit: PhysicsUnit,
    rng: np.random.Generator,
    schedule: list[ChamberSession] | None = None,
    steps: pd.DataFrame | None = None,
    rate_hz: float = 50.0,
    lot: str = "CH",
    unit_id: str = "U000",
) -> list[ChamberSessionInput]:
    """The sessions averaged by :func:`schemas.averaging.step_means_from_tables`, as the
    thermal fit takes them."""
    steps = steps if steps is not None else chamber_steps()
    out = []
    for s, samples, md in chamber_sessions(unit, rng, schedule, steps, rate_hz, unit_id):
        sm, _ = step_means_from_tables(SessionKey(lot, unit_id, s.order + 1), steps, samples, md)
        out.append(ChamberSessionInput(sm, s.setpoint_c, 1 if s.sweep == "heating" else -1))
    return out


def held_out_session(
    unit: PhysicsUnit,
    rng: np.random.Generator,
    setpoint_c: float,
    steps: pd.DataFrame | None = None,
    rate_hz: float = 50.0,
    from_c: float | None = None,
) -> StepMeans:
    """One soaked session at a temperature between the setpoints (not in any fit)."""
    steps = steps if steps is not None else chamber_steps()
    soak = ChamberSoak(setpoint_c=setpoint_c, from_c=setpoint_c - 10.0 if from_c is None else from_c)
    samples, md = simulate_physics_session(with_soak(unit, soak), steps, rng, rate_hz=rate_hz)
    sm, _ = step_means_from_tables(SessionKey("CH", "HELD", 99), steps, samples, md)
    return sm


def write_chamber_unit(
    root: Path | str,
    unit: PhysicsUnit,
    rng: np.random.Generator,
    lot: str,
    unit_id: str,
    schedule: list[ChamberSession] | None = None,
    steps: pd.DataFrame | None = None,
    rate_hz: float = 50.0,
) -> list[Path]:
    """Write every session of a unit's chamber run in the acquisition contract."""
    steps = steps if steps is not None else chamber_steps()
    return [
        write_session(root, SessionKey(lot, unit_id, s.order + 1), steps, samples, md)
        for s, samples, md in chamber_sessions(unit, rng, schedule, steps, rate_hz, unit_id)
    ]


def simulate_chamber_fleet(
    out: Path | str,
    lots: int,
    units: int,
    seed: int,
    reps: int = 2,
    rate_hz: float = 50.0,
    out_of_limit: int = 0,
) -> dict:
    """Write a thermal fleet (``mimucal simulate --physics --chamber``): every unit a chamber
    run of 7 setpoints -40..85 degC and ``reps`` alternating sweeps; units cycle through
    linear, linear + hysteresis, cubic, cubic + hysteresis. ``out_of_limit``: that many
    units (the first of each lot first) get a gyro bias coefficient of 0.02 deg/s/degC on x.
    Writes ``OUT/fleet.json`` (format ``mimucal-chamber-fleet``) with each unit's kind and
    sensor thermal coefficients; returns it."""
    import json

    from calib_core.sim.chamber import thermal_physics_unit

    root = Path(out)
    rng = np.random.default_rng(seed)
    schedule = chamber_schedule(reps=reps)
    steps = chamber_steps()
    doc = {
        "format": "mimucal-chamber-fleet",
        "seed": seed,
        "setpoints_c": sorted({s.setpoint_c for s in schedule}),
        "reps": reps,
        "sample_rate_hz": rate_hz,
        "units": [],
    }
    k = 0
    for lot_i in range(lots):
        lot = f"T{lot_i + 1:02d}"
        for u_i in range(units):
            k += 1
            unit_id = f"U{k:04d}"
            cubic, hyst = bool((k - 1) % 4 >= 2), bool((k - 1) % 2)
            unit = thermal_physics_unit(rng, cubic=cubic, hysteresis=hyst)
            bad = len([x for x in doc["units"] if x["out_of_limit"]]) < out_of_limit and u_i == 0
            if bad:
                unit = unit.replace_gyro(0, bias_tc=0.02)
            write_chamber_unit(root, unit, rng, lot, unit_id, schedule, steps, rate_hz)
            doc["units"].append(
                {
                    "lot": lot,
                    "unit": unit_id,
                    "kind": ("cubic" if cubic else "linear") + (" + hysteresis" if hyst else ""),
                    "out_of_limit": bad,
                    "gyro_bias_tc": [g.bias_tc for g in unit.gyros],
                    "accel_bias_tc": [a.bias_tc for a in unit.accels],
                }
            )
    root.mkdir(parents=True, exist_ok=True)
    (root / "fleet.json").write_text(json.dumps(doc, indent=2) + "\n")
    return doc
