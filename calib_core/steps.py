"""Per-step averages of one session: the boundary between reading data and fitting models.

Everything in ``calib_core`` consumes :class:`StepMeans`; ``schemas.averaging`` produces it
from raw Parquet, and ``calib_core.sim.simulator.simulate_step_means`` produces it directly (fast
path for Monte Carlo tests). Only *usable* steps are in it: saturated or too-short steps were
already removed and named as warnings by the producer.

Units inside: gyro channels are either ``deg/s`` (rad/s is converted at the boundary) or a raw
unit (``LSB``, ``V``) that the fitted matrices absorb; accelerometer channels are ``g``
(m/s^2 converted with the session's local gravity) or raw. References are always deg/s and g.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

TESTS = ("stationary", "multirate", "multiposition", "dynamic", "verification")
UP_AXES = ("+x", "-x", "+y", "-y", "+z", "-z")
GYRO_UNITS = ("deg/s", "LSB", "V")  # after boundary conversion (rad/s -> deg/s)
ACCEL_UNITS = ("g", "LSB", "V")  # after boundary conversion (m/s^2 -> g)


@dataclass(frozen=True)
class SessionKey:
    """Identity of one session (one lot/unit/rep directory)."""

    lot: str
    unit: str
    rep: int

    def __str__(self) -> str:  # used verbatim in every error message
        return f"lot={self.lot}/unit={self.unit}/rep={self.rep}"


_ROW_FIELDS = (
    "step",
    "test",
    "up_axis",
    "rate_dps",
    "angle_deg",
    "w_ref",
    "f_ref",
    "gyro",
    "accel",
    "gyro_std",
    "accel_std",
    "count",
    "t_mid",
    "temp_c",
)


@dataclass(frozen=True)
class StepMeans:
    """Averaged sensor outputs and nominal references, one row per usable step.

    Arrays are aligned on the first axis (n steps). ``gyro``/``accel`` are the mean raw
    outputs after boundary unit conversion; ``*_std`` the within-step sample standard
    deviation; ``count`` the number of samples averaged (after settling).
    """

    key: SessionKey
    step: np.ndarray  # (n,) int
    test: np.ndarray  # (n,) str, one of TESTS
    up_axis: np.ndarray  # (n,) str, one of UP_AXES
    rate_dps: np.ndarray  # (n,) commanded table rate, deg/s
    angle_deg: np.ndarray  # (n,) multiposition angle, NaN otherwise
    w_ref: np.ndarray  # (n, 3) nominal body rate, deg/s
    f_ref: np.ndarray  # (n, 3) nominal specific force at rotation centre, g
    gyro: np.ndarray  # (n, 3) mean raw gyro output
    accel: np.ndarray  # (n, 3) mean raw accelerometer output
    gyro_std: np.ndarray  # (n, 3) within-step sample std
    accel_std: np.ndarray  # (n, 3)
    count: np.ndarray  # (n,) samples averaged
    t_mid: np.ndarray  # (n,) mid time of the averaged window, s since session start
    temp_c: np.ndarray  # (n,) mean temperature, NaN when not recorded
    gyro_unit: str = "deg/s"
    accel_unit: str = "g"
    g_local: float = 9.80665
    sample_rate_hz: float = 100.0
    gyro_range_dps: tuple[float, float, float] = (300.0, 300.0, 3600.0)
    accel_range_g: tuple[float, float, float] = (50.0, 50.0, 50.0)
    metadata: dict[str, Any] = field(default_factory=dict)  # provenance (session_start, ...)
    # the step's heading (optional steps column heading_deg, degrees; None: all 0) and where
    # the table stands (optional metadata): what the Earth rate's body direction depends on
    heading_deg: np.ndarray | None = None
    latitude_deg: float | None = None
    table_heading_deg: float | None = None
    settle_s: np.ndarray | None = None  # (n,) the steps' settling time (None: not known)

    def __post_init__(self) -> None:
        n = len(self.step)
        for name in ("test", "up_axis", "rate_dps", "angle_deg", "count", "t_mid", "temp_c"):
            if len(getattr(self, name)) != n:
                raise ValueError(f"StepMeans.{name} has {len(getattr(self, name))} rows, expected {n}")
        if self.heading_deg is not None and len(self.heading_deg) != n:
            raise ValueError(f"StepMeans.heading_deg has {len(self.heading_deg)} rows, expected {n}")
        for name in ("w_ref", "f_ref", "gyro", "accel", "gyro_std", "accel_std"):
            if getattr(self, name).shape != (n, 3):
                raise ValueError(f"StepMeans.{name} has shape {getattr(self, name).shape}, expected ({n}, 3)")

    def __len__(self) -> int:
        return len(self.step)

    def select(self, mask: np.ndarray) -> StepMeans:
        """Rows where ``mask`` is true (boolean array or index array)."""
        idx = np.asarray(mask)
        rows = _ROW_FIELDS + tuple(f for f in ("heading_deg", "settle_s") if getattr(self, f) is not None)
        if idx.ndim != 1:  # not a row mask or index list: let __init__ check the result
            return replace(self, **{name: getattr(self, name)[idx] for name in rows})
        state = {name: v for name, v in self.__dict__.items() if name != "_subsets"}
        for name in rows:
            state[name] = state[name][idx]
        # rows of a valid StepMeans are a valid StepMeans: no need to run the shape checks
        # of __init__ again (this is called a few times for every session)
        out = object.__new__(type(self))
        out.__dict__.update(state)
        return out

    def of_test(self, *tests: str) -> StepMeans:
        """Rows of the given tests (the same object on every call with the same tests)."""
        # every fit of a session asks for the same few subsets: each is built once and kept
        # on the instance (the arrays are never modified after construction)
        subsets = self.__dict__.get("_subsets")
        if subsets is None:
            subsets = {}
            object.__setattr__(self, "_subsets", subsets)
        sub = subsets.get(tests)
        if sub is None:
            sub = subsets[tests] = self.select(self.rows_of_test(*tests))
        return sub

    def rows_of_test(self, *tests: str) -> np.ndarray:
        """Indices of the rows of the given tests, in row order."""
        return np.flatnonzero(np.isin(self.test, tests))

    def __getstate__(self) -> dict:  # the subsets are a cache: not pickled
        state = dict(self.__dict__)
        state.pop("_subsets", None)
        return state

    @property
    def headings(self) -> np.ndarray:
        """Each step's heading, degrees (0 where the steps table has no heading_deg)."""
        return np.zeros(len(self)) if self.heading_deg is None else np.asarray(self.heading_deg, float)

    def turned_deg(self) -> np.ndarray:
        """(n, 2) angle the table has turned since the step started, at the start and the end
        of the averaged window, degrees, by the orientation convention (docs/data-contract.md:
        the commanded rate is reached by a linear ramp over the first half of the settling
        time, averaging starts after it); zeros where the settling time is not known."""
        out = np.zeros((len(self), 2))
        if self.settle_s is None:
            return out
        rate = np.asarray(self.rate_dps, float)
        settle = np.asarray(self.settle_s, float)
        window = np.asarray(self.count, float) / float(self.sample_rate_hz)
        out[:, 0] = 0.75 * settle * rate
        out[:, 1] = out[:, 0] + window * rate
        return out


def stack_field(sms: Sequence[StepMeans], name: str) -> np.ndarray:
    """Field ``name`` of every session (sessions of one step layout), stacked on a leading
    axis: (R, n) or (R, n, 3), for the fits that run a unit's repetitions together."""
    return np.stack([getattr(sm, name) for sm in sms])
