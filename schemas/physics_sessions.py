"""Sessions of the physics simulator (:mod:`calib_core.sim.physics`) through the real contract
path: samples are validated and averaged by the reader's own code, or written as Parquet.

Why here and not in calib_core: turning samples into step means is the reader's job
(:mod:`schemas.averaging`), and calib_core may not import schemas.
"""

from __future__ import annotations

from dataclasses import replace
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


def _sessions(unit, steps, rng, n_reps, rate_hz, table, back_to_back, rep_gap_s, ambient_sd_c=0.0):
    """(rep, samples, metadata) of each repetition: one a day from a cold start, or
    ``back_to_back`` after one power-on (each ``rep_gap_s`` after the last ended; the unit
    stays warm, a new turn-on bias is drawn). ``ambient_sd_c``: each cold start's ambient
    (the warm-up's start) drawn around the unit's, a lab whose temperature differs from day
    to day."""
    power_on = 0.0
    t0 = pd.Timestamp("2026-11-01T02:00:00Z")
    for rep in range(1, n_reps + 1):
        start = (t0 + pd.Timedelta(seconds=power_on)).strftime("%Y-%m-%dT%H:%M:%SZ")
        today = unit
        if ambient_sd_c and unit.temperature is not None and not back_to_back:
            warm = replace(unit.temperature, start_c=unit.temperature.start_c + rng.normal(0.0, ambient_sd_c))
            today = replace(unit, temperature=warm)
        samples, md = simulate_physics_session(
            today,
            steps,
            rng,
            rate_hz=rate_hz,
            table=table,
            session_start=start if back_to_back else _session_start(rep),
            power_on_s=power_on if back_to_back else 0.0,
        )
        if back_to_back:
            power_on += float(samples["t"].iloc[-1]) + 1.0 / rate_hz + rep_gap_s
        yield rep, samples, md


def physics_unit_step_means(
    unit: PhysicsUnit,
    steps: pd.DataFrame,
    rng: np.random.Generator,
    n_reps: int = 5,
    rate_hz: float = 50.0,
    table: Turntable = Turntable(),
    lot: str = "PHYS",
    unit_id: str = "U000",
    back_to_back: bool = False,
    rep_gap_s: float = 60.0,
    ambient_sd_c: float = 0.0,
) -> list[StepMeans]:
    """Step means of ``n_reps`` repetitions (each with its own turn-on biases and noise; a
    cold start each, at an ambient drawn with ``ambient_sd_c``, or ``back_to_back`` on one
    warm-up), averaged by :func:`schemas.averaging.step_means_from_tables`."""
    out = []
    reps = _sessions(unit, steps, rng, n_reps, rate_hz, table, back_to_back, rep_gap_s, ambient_sd_c)
    for rep, samples, md in reps:
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
    back_to_back: bool = False,
    rep_gap_s: float = 60.0,
) -> list[Path]:
    """Write ``n_reps`` repetitions of one unit in the acquisition contract under ``root``."""
    return [
        write_session(root, SessionKey(lot, unit_id, rep), steps, samples, md)
        for rep, samples, md in _sessions(unit, steps, rng, n_reps, rate_hz, table, back_to_back, rep_gap_s)
    ]
