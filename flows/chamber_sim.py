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
