"""What every catalogue effect shares: the motion it depends on, the unit's sensing geometry
it acts through, the term interface and the registry.

An effect is an error in what one *sensor* senses, in that sensor's own physical unit (deg/s
for a gyro, g for an accelerometer), linear in the effect's parameters given the motion and
the sensing geometry:

    sensor j senses   a_j . q_j + e_j(motion, geometry) @ theta

(a_j its unit sensing direction, q_j the rate or the specific force at its position). The
unit outputs raw_j = scale_j (a_j . q_j + e_j + bias_j), and a calibration K (physical per
raw, K = S^-1 with the rows of S = scale_j a_j) turns the sensor errors into errors on the
six calibrated channels through the sensing geometry:

    K raw = q + A^-1 e + b          (A: rows a_j, one 3x3 per sensor triad)

so an error of one sensor leaks into the other channels exactly as far as the sensors are
misaligned (:meth:`SensingGeometry.to_body`). The geometry comes from the fitted K
(:meth:`SensingGeometry.from_gains`): the model is bilinear in (K, theta) and discovery
re-linearises it until the geometry settles.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from dataclasses import dataclass
from typing import ClassVar

import numpy as np

CHANNELS = ("gx", "gy", "gz", "ax", "ay", "az")
GYRO = slice(0, 3)
ACCEL = slice(3, 6)
DEG = np.pi / 180.0
THERMAL_REF_C = 25.0  # temperature coefficients are per degC from here


def skew(v: np.ndarray) -> np.ndarray:
    """Cross-product matrices of rows of v: (n, 3) -> (n, 3, 3), skew(a) @ b = a x b."""
    v = np.atleast_2d(v)
    # filled in place (nine stacks of columns cost more than the matrices, called per session)
    out = np.zeros((len(v), 3, 3), dtype=np.result_type(v.dtype, np.float64))
    out[:, 0, 1], out[:, 0, 2] = -v[:, 2], v[:, 1]
    out[:, 1, 0], out[:, 1, 2] = v[:, 2], -v[:, 0]
    out[:, 2, 0], out[:, 2, 1] = -v[:, 1], v[:, 0]
    return out


def sensor_zeros(n: int, p: int) -> np.ndarray:
    """Zeros (n, 6, p) for a term's sensor regressors, laid out sensor by sensor in memory (a
    (6, n, p) array seen as (n, 6, p)): discovery takes each sensor triad's rows as one
    block (:func:`calib_core.discovery.design.term_design`)."""
    return np.zeros((6, n, p)).transpose(1, 0, 2)


@dataclass(frozen=True)
class MotionContext:
    """What the effects depend on, per row (a step mean or a sample).

    ``w`` deg/s and ``f`` g are body-frame rate and specific force at the rotation centre;
    ``dwdt`` deg/s^2 is the angular acceleration (zero on constant-rate steps); ``temp_c`` is
    NaN where not recorded; ``t`` is seconds since session start. ``heading_deg`` is each
    step's heading (the steps' optional column, 0 without it); ``latitude_deg`` and
    ``table_heading_deg`` where the table stands (optional metadata, None when not given):
    docs/data-contract.md, "Orientation convention".
    """

    w: np.ndarray  # (n, 3) deg/s
    f: np.ndarray  # (n, 3) g
    dwdt: np.ndarray  # (n, 3) deg/s^2
    temp_c: np.ndarray  # (n,)
    t: np.ndarray  # (n,)
    g_local: float = 9.80665
    heading_deg: np.ndarray | None = None  # (n,); None: 0 everywhere
    latitude_deg: float | None = None
    table_heading_deg: float | None = None
    # (n, 2) angle turned since the step's start at the start and end of the averaged
    # window, deg (StepMeans.turned_deg); None: not known
    turned_deg: np.ndarray | None = None

    @classmethod
    def from_refs(
        cls,
        w,
        f,
        temp_c=None,
        t=None,
        dwdt=None,
        g_local=9.80665,
        heading_deg=None,
        latitude_deg=None,
        table_heading_deg=None,
        turned_deg=None,
    ) -> MotionContext:
        w = np.atleast_2d(np.asarray(w, dtype=float))
        n = len(w)
        return cls(
            w=w,
            f=np.atleast_2d(np.asarray(f, dtype=float)),
            dwdt=np.zeros((n, 3)) if dwdt is None else np.atleast_2d(np.asarray(dwdt, float)),
            temp_c=np.full(n, np.nan) if temp_c is None else np.asarray(temp_c, float),
            t=np.zeros(n) if t is None else np.asarray(t, float),
            g_local=float(g_local),
            heading_deg=np.zeros(n) if heading_deg is None else np.asarray(heading_deg, float),
            latitude_deg=None if latitude_deg is None else float(latitude_deg),
            table_heading_deg=None if table_heading_deg is None else float(table_heading_deg),
            turned_deg=None if turned_deg is None else np.asarray(turned_deg, float),
        )

    def __len__(self) -> int:
        return len(self.w)


@dataclass(frozen=True)
class SensingGeometry:
    """Unit sensing directions of the three gyros and three accelerometers (rows, body
    frame). Identity: every sensor on its nominal body axis."""

    gyro_axes: np.ndarray  # (3, 3) row j = gyro j's sensing direction
    accel_axes: np.ndarray  # (3, 3)

    @classmethod
    def identity(cls) -> SensingGeometry:
        return _IDENTITY

    @classmethod
    def from_gains(cls, K_g: np.ndarray, K_a: np.ndarray) -> SensingGeometry:
        """From a calibration's gains (physical per raw): the rows of K^-1 are each sensor's
        scale times its sensing direction."""

        def axes(K):
            S = np.linalg.inv(np.asarray(K, float))
            return S / np.linalg.norm(S, axis=1, keepdims=True)

        return cls(axes(K_g), axes(K_a))

    def sensor_inputs(self, ctx: MotionContext) -> tuple[np.ndarray, np.ndarray]:
        """Each sensor's own input at the rotation centre: a_j . w (deg/s) and a_j . f (g)."""
        return ctx.w @ self.gyro_axes.T, ctx.f @ self.accel_axes.T

    def to_body(self, E: np.ndarray) -> np.ndarray:
        """Sensor errors (n, 6, p) -> errors on the calibrated channels, A^-1 e per triad."""
        out = np.empty_like(E)
        np.einsum("ij,njp->nip", self.inverse("gyro"), E[:, GYRO], out=out[:, GYRO])
        np.einsum("ij,njp->nip", self.inverse("accel"), E[:, ACCEL], out=out[:, ACCEL])
        return out

    def inverse(self, which: str) -> np.ndarray:
        """A^-1 of the ``which`` triad ("gyro" or "accel"), what :meth:`to_body` applies
        (kept)."""
        key = f"_inv_{which}"
        if key not in self.__dict__:  # frozen dataclass: kept beside the fields
            object.__setattr__(self, key, np.linalg.inv(getattr(self, f"{which}_axes")))
        return self.__dict__[key]

    def distance(self, other: SensingGeometry) -> float:
        """Largest change of a sensing direction, rad (small angles)."""
        return float(
            max(
                np.abs(self.gyro_axes - other.gyro_axes).max(),
                np.abs(self.accel_axes - other.accel_axes).max(),
            )
        )


_IDENTITY = SensingGeometry(np.eye(3), np.eye(3))


@dataclass(frozen=True)
class FigureVariable:
    """What a report plots an effect's residual against, per row."""

    label: str  # e.g. "rate on the gyro's own axis"
    unit: str  # e.g. "deg/s"
    values: np.ndarray  # (n,)


class EffectTerm(ABC):
    """One named physical effect. A subclass (one module per effect) sets the class
    attributes and implements :meth:`sensor_regressors`, :meth:`realistic`,
    :meth:`physics_knobs` and :meth:`figure_variable`."""

    name: ClassVar[str]  # catalogue name, e.g. "lever_arm"
    description: ClassVar[str]  # one-line label
    param_names: ClassVar[tuple[str, ...]]
    param_units: ClassVar[tuple[str, ...]]
    excited_by: ClassVar[str]  # which steps make it visible
    # a parameter whose standard error on the unit's steps exceeds this (parameter units) is
    # "undetermined": the protocol cannot tell a realistic value from zero
    max_useful_stderr: ClassVar[float]
    # False for an effect of where the unit is measured (the Earth's rotation), not of its
    # sensors: discovery fits it, a calibration applied to the unit's outputs never removes it
    sensor_effect: ClassVar[bool] = True
    # True for an effect known to be present whatever its size (the Earth's rotation): named
    # once significant and improving the held-out score, without the rule that it must fix a
    # channel that misfit by a practically meaningful gain (that rule keeps small sensor
    # defects out; here the question is only which explanation the data support)
    named_when_significant: ClassVar[bool] = False

    @property
    def n_params(self) -> int:
        return len(self.param_names)

    @abstractmethod
    def sensor_regressors(self, ctx: MotionContext, geometry: SensingGeometry) -> np.ndarray:
        """d(error sensed by sensor j)/d(theta), (n, 6, n_params), in each sensor's own
        physical unit (rows 0-2 the gyros, 3-5 the accelerometers)."""

    def regressors(self, ctx: MotionContext, geometry: SensingGeometry | None = None) -> np.ndarray:
        """d(calibrated channel error)/d(theta), (n, 6, n_params): the sensor errors through
        the sensing geometry (identity when not given)."""
        g = SensingGeometry.identity() if geometry is None else geometry
        return g.to_body(np.asarray(self.sensor_regressors(ctx, g), float))

    def error(
        self, ctx: MotionContext, theta: np.ndarray, geometry: SensingGeometry | None = None
    ) -> np.ndarray:
        """Additive error on the six calibrated channels, (n, 6)."""
        return self.regressors(ctx, geometry) @ np.asarray(theta, dtype=float)

    def param_sensor(self) -> np.ndarray:
        """The sensor (0-5) each parameter acts on, (n_params,)."""
        probe = MotionContext.from_refs(
            w=[[100.0, -200.0, 300.0]],
            f=[[0.3, -0.5, 0.8]],
            temp_c=[30.0],
            t=[100.0],
            dwdt=[[10.0, 20.0, 30.0]],
        )
        E = np.abs(self.sensor_regressors(probe, SensingGeometry.identity())[0])
        return np.argmax(E, axis=0)

    # -- realistic size and the independent simulator --------------------------------------
    @abstractmethod
    def realistic(self, rng: np.random.Generator, scale: float = 1.0) -> tuple[np.ndarray, str]:
        """Parameters of the effect at ``scale`` times a realistic size, on random sensors,
        and a description of where it was put."""

    @abstractmethod
    def physics_knobs(self, theta: np.ndarray) -> dict[tuple[str, int], dict[str, object]]:
        """The physical sensor settings of :mod:`calib_core.sim.physics` that produce this
        effect with parameters ``theta``: {("gyro" | "accel", sensor index): {field: value}}."""

    def table_knobs(self, theta: np.ndarray) -> dict[str, object]:
        """Settings of :class:`calib_core.sim.physics.Turntable` that produce this effect (an
        effect of where the table stands); {} for an effect of the sensors."""
        return {}

    def hide(self, unit, rng: np.random.Generator, scale: float = 1.0):
        """A :class:`calib_core.sim.physics.PhysicsUnit` with this effect hidden in its
        sensors at ``scale`` times a realistic size; returns (unit, theta, description)."""
        theta, what = self.realistic(rng, scale)
        for (kind, i), changes in self.physics_knobs(theta).items():
            unit = getattr(unit, f"replace_{kind}")(i, **changes)
        return unit, theta, what

    @abstractmethod
    def figure_variable(self, ctx: MotionContext, channel: int) -> FigureVariable:
        """What the residual of ``channel`` is plotted against to show this effect."""


_CATALOGUE: dict[str, type[EffectTerm]] = {}


def register_effect(cls: type[EffectTerm]) -> type[EffectTerm]:
    """Class decorator: add an effect to the catalogue under ``cls.name``."""
    if cls.name in _CATALOGUE and _CATALOGUE[cls.name] is not cls:
        raise ValueError(f"effect {cls.name!r} registered twice")
    _CATALOGUE[cls.name] = cls
    return cls


def unregister_effect(name: str) -> None:
    """Remove an effect from the catalogue (tests that register a temporary one)."""
    _CATALOGUE.pop(name, None)


def catalogue() -> dict[str, type[EffectTerm]]:
    """All registered effects by name."""
    return dict(_CATALOGUE)


def get_effect(name: str) -> EffectTerm:
    try:
        return _CATALOGUE[name]()
    except KeyError:
        raise KeyError(f"unknown effect {name!r}; known: {sorted(_CATALOGUE)}") from None


def total_error(
    ctx: MotionContext, effects: list[tuple[EffectTerm, np.ndarray]], geometry: SensingGeometry | None = None
) -> np.ndarray:
    """Sum of several effects' errors on the calibrated channels, (n, 6)."""
    out = np.zeros((len(ctx), 6))
    for term, theta in effects:
        out += term.error(ctx, theta, geometry)
    return out


def up_direction(ctx: MotionContext) -> np.ndarray:
    """Body direction of the world vertical per row: the specific force at rest is 1 g up
    (the rotation axis where no specific force is given)."""
    f = ctx.f
    n = np.linalg.norm(f, axis=1, keepdims=True)
    wn = np.linalg.norm(ctx.w, axis=1, keepdims=True)
    up = np.where(
        n > 1e-9,
        f / np.where(n > 1e-9, n, 1.0),
        np.where(wn > 0, ctx.w / np.where(wn > 0, wn, 1.0), [0.0, 0.0, 1.0]),
    )
    return up


def heading_reference(up: np.ndarray) -> np.ndarray:
    """Per row, the body axis least aligned with ``up`` projected on the horizontal plane:
    the direction a step's heading is measured from (docs/data-contract.md)."""
    e = np.eye(3)[np.argmin(np.abs(up), axis=1)]
    h = e - np.sum(e * up, axis=1, keepdims=True) * up
    return h / np.linalg.norm(h, axis=1, keepdims=True)


def turn_about(v: np.ndarray, axis: np.ndarray, angle_rad: np.ndarray) -> np.ndarray:
    """Rows of v turned right-handedly about unit rows ``axis`` by ``angle_rad`` (Rodrigues)."""
    c, s = np.cos(angle_rad)[:, None], np.sin(angle_rad)[:, None]
    return v * c + np.cross(axis, v) * s + axis * np.sum(axis * v, axis=1, keepdims=True) * (1.0 - c)


def random_sign(rng: np.random.Generator) -> float:
    return float(rng.choice([-1.0, 1.0]))
