"""Physical effects as named model terms: the catalogue that model discovery searches.

An effect is an additive error on the *physical* outputs of the unit, linear in its own
parameters given the motion (rate, specific force, angular acceleration, temperature, time):

    sensed = true + E(motion) @ theta            (6 channels: gx gy gz in deg/s, ax ay az in g)

The simulator adds it to the truth; the fits and the discovery step estimate ``theta`` jointly
with the base model because it is linear; compensation subtracts it. A new effect is one new
subclass registered with :func:`register_effect`; nothing else changes.
"""
from __future__ import annotations

from abc import ABC, abstractmethod
from dataclasses import dataclass
from typing import ClassVar

import numpy as np

CHANNELS = ("gx", "gy", "gz", "ax", "ay", "az")
GYRO = slice(0, 3)
ACCEL = slice(3, 6)


@dataclass(frozen=True)
class MotionContext:
    """What the effects depend on, per row (a step mean or a sample).

    ``w`` deg/s and ``f`` g are body-frame rate and specific force at the rotation centre;
    ``dwdt`` deg/s^2 is the angular acceleration (zero on constant-rate steps); ``temp_c`` is
    NaN where not recorded; ``t`` is seconds since session start.
    """

    w: np.ndarray  # (n, 3) deg/s
    f: np.ndarray  # (n, 3) g
    dwdt: np.ndarray  # (n, 3) deg/s^2
    temp_c: np.ndarray  # (n,)
    t: np.ndarray  # (n,)
    g_local: float = 9.80665

    @classmethod
    def from_refs(cls, w, f, temp_c=None, t=None, dwdt=None, g_local=9.80665) -> "MotionContext":
        w = np.atleast_2d(np.asarray(w, dtype=float))
        n = len(w)
        return cls(
            w=w,
            f=np.atleast_2d(np.asarray(f, dtype=float)),
            dwdt=np.zeros((n, 3)) if dwdt is None else np.atleast_2d(np.asarray(dwdt, float)),
            temp_c=np.full(n, np.nan) if temp_c is None else np.asarray(temp_c, float),
            t=np.zeros(n) if t is None else np.asarray(t, float),
            g_local=float(g_local),
        )

    def __len__(self) -> int:
        return len(self.w)


class EffectTerm(ABC):
    """One named physical effect. Subclasses set the class attributes and ``regressors``."""

    name: ClassVar[str]  # catalogue name, e.g. "lever_arm"
    description: ClassVar[str]
    param_names: ClassVar[tuple[str, ...]]
    param_units: ClassVar[tuple[str, ...]]

    @property
    def n_params(self) -> int:
        return len(self.param_names)

    @abstractmethod
    def regressors(self, ctx: MotionContext) -> np.ndarray:
        """d(sensed - true)/d(theta): array (n, 6, n_params), physical units per channel."""

    def error(self, ctx: MotionContext, theta: np.ndarray) -> np.ndarray:
        """Additive error on the six physical channels, (n, 6)."""
        return self.regressors(ctx) @ np.asarray(theta, dtype=float)

    def channels(self) -> tuple[int, ...]:
        """Channels this term can touch (for reports and residual selection)."""
        probe = MotionContext.from_refs(
            w=[[100.0, -200.0, 300.0]], f=[[0.3, -0.5, 0.8]], temp_c=[30.0], t=[100.0],
            dwdt=[[10.0, 20.0, 30.0]],
        )
        touched = np.abs(self.regressors(probe)[0]).sum(axis=1) > 0
        return tuple(int(i) for i in np.flatnonzero(touched))


_CATALOGUE: dict[str, type[EffectTerm]] = {}


def register_effect(cls: type[EffectTerm]) -> type[EffectTerm]:
    """Class decorator: add an effect to the catalogue under ``cls.name``."""
    if cls.name in _CATALOGUE and _CATALOGUE[cls.name] is not cls:
        raise ValueError(f"effect {cls.name!r} registered twice")
    _CATALOGUE[cls.name] = cls
    return cls


def catalogue() -> dict[str, type[EffectTerm]]:
    """All registered effects by name (importing calib_core.effect_terms fills it)."""
    from calib_core import effect_terms  # noqa: F401  (registers the built-in terms)

    return dict(_CATALOGUE)


def get_effect(name: str) -> EffectTerm:
    try:
        return catalogue()[name]()
    except KeyError:
        raise KeyError(f"unknown effect {name!r}; known: {sorted(catalogue())}") from None


def total_error(ctx: MotionContext, effects: list[tuple[EffectTerm, np.ndarray]]) -> np.ndarray:
    """Sum of several effects' errors, (n, 6)."""
    out = np.zeros((len(ctx), 6))
    for term, theta in effects:
        out += term.error(ctx, theta)
    return out
