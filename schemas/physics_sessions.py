"""Sessions of the physics simulator (:mod:`calib_core.sim.physics`) through the real contract
path: samples are validated and averaged by the reader's own code, or written as Parquet.

Why here and not in calib_core: turning samples into step means is the reader's job
(:mod:`schemas.averaging`), and calib_core may not import schemas.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd

from calib_core.sim.physics import PhysicsUnit, Turntable, simulate_physics_session
from calib_core.steps import SessionKey, StepMeans
from schemas.averaging import step_means_from_tables
from schemas.writer import write_session


def _session_start(rep: int) -> str:
    # one repetition a day, as on a production line that retests a unit daily
    return f"2026-11-{min(rep, 28):02d}T02:00:00Z"


def physics_unit_step_means(
    unit: PhysicsUnit,
    steps: pd.DataFrame,
    rng: np.random.Generator,
    n_reps: int = 5,
    rate_hz: float = 50.0,
    table: Turntable = Turntable(),
    lot: str = "PHYS",
    unit_id: str = "U000",
) -> list[StepMeans]:
    """Step means of ``n_reps`` repetitions (each a cold start with its own turn-on biases
    and noise), averaged by :func:`schemas.averaging.step_means_from_tables`."""
    out = []
    for rep in range(1, n_reps + 1):
        samples, md = simulate_physics_session(
            unit, steps, rng, rate_hz=rate_hz, table=table, session_start=_session_start(rep)
        )
        sm, _warnings = step_means_from_tables(SessionKey(lot, unit_id, rep), steps, samples, md)
        out.append(sm)
    return out


def write_physics_unit(
    root: Path | str,
    unit: PhysicsUnit,
    steps: pd.DataFrame,
    rng: np.random.Generator,
    n_reps: int = 5,
    rate_hz: float = 50.0,
    table: Turntable = Turntable(),
    lot: str = "PHYS",
    unit_id: str = "U000",
) -> list[Path]:
    """Write ``n_reps`` repetitions of one unit in the acquisition contract under ``root``."""
    dirs = []
    for rep in range(1, n_reps + 1):
        samples, md = simulate_physics_session(
            unit, steps, rng, rate_hz=rate_hz, table=table, session_start=_session_start(rep)
        )
        dirs.append(write_session(root, SessionKey(lot, unit_id, rep), steps, samples, md))
    return dirs
