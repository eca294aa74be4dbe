"""How well discovery names effects hidden in the independent physics simulator
(:mod:`calib_core.sim.physics`): the scenarios and the tally behind the figures of
docs/model-discovery.md (``tools/model_discovery_figures.py physics``) and their seeded tests.

A scenario is a realistic clean unit (sensors misaligned by about 0.5 deg, warm-up ramp)
with catalogue effects hidden in its sensors by each effect's own
:meth:`calib_core.effects.EffectTerm.hide`, or with one physical error that no catalogue
term models (:data:`OUT_OF_CATALOGUE`). Step means come from a caller-given function (the
reader's averaging lives in ``schemas.physics_sessions``).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
import pandas as pd

from calib_core.discovery.detection import DetectionLimits
from calib_core.discovery.turntable import diagnose_unit
from calib_core.effects import get_effect
from calib_core.sim.physics import PhysicsUnit, Turntable, typical_physics_unit

StepMeansOf = Callable[[PhysicsUnit, pd.DataFrame, np.random.Generator, str], list]


def _periodic(unit, rng, scale):
    i = int(rng.integers(3))
    amp = rng.choice([-1.0, 1.0]) * rng.uniform(0.03, 0.08) * scale
    return unit.replace_gyro(
        i, periodic_amp=float(amp), periodic_period_dps=130.0
    ), f"gyro {'xyz'[i]} periodic {amp:.3g} deg/s, period 130 deg/s"


def _cross_quad(unit, rng, scale):
    # gyro x or y picks up the square of the z rate (the axis turned to 3600 deg/s)
    i = int(rng.integers(2))
    k = rng.choice([-1.0, 1.0]) * rng.uniform(1e-8, 3e-8) * scale
    return unit.replace_gyro(i, cross_quad=(0.0, 0.0, float(k))), f"gyro {'xyz'[i]} += {k:.2g} w_z^2"


def _random_walk(unit, rng, scale):
    i = int(rng.integers(3))
    rw = rng.uniform(5e-4, 1e-3) * scale
    return unit.replace_gyro(
        i, random_walk=float(rw)
    ), f"gyro {'xyz'[i]} bias random walk {rw:.2g} deg/s/sqrt(s)"


# physical errors no catalogue term models: name -> (unit, rng, scale) -> (unit, description)
OUT_OF_CATALOGUE = {
    "periodic_rate_error": _periodic,
    "rate_squared_cross_coupling": _cross_quad,
    "bias_random_walk": _random_walk,
}

PAIRS = (
    ("lever_arm", "gyro_g_sensitivity"),
    ("gyro_scale_asymmetry", "accel_scale_nonlinearity"),
    ("gyro_scale_nonlinearity", "thermal_bias_drift"),
)


@dataclass
class Tally:
    """Outcome of one scenario over its units."""

    hidden: tuple[str, ...]
    n: int = 0
    exact: int = 0  # named exactly the hidden catalogue effects
    extra: int = 0  # named a catalogue effect that was not hidden
    misfit: int = 0
    unexplained: int = 0
    any_named: int = 0
    confounded: int = 0  # reported a confounded group
    confounded_hidden: int = 0  # ... holding every hidden effect, and nothing named alone
    gains: list[float] = field(default_factory=list)
    seconds: float = 0.0
    misses: list[str] = field(default_factory=list)  # what was named instead, per miss
    # the hidden effect against the protocol's detection limit (run_scenario's ``limits``):
    # units whose effect is detected with the limits' power and worth naming, and of them
    # those named exactly right; below the limit, the units given another catalogue name
    within: int = 0
    within_exact: int = 0
    within_confounded: int = 0  # ... reported in a confounded group instead, nothing named
    below_extra: int = 0

    def add(self, d, what: str, within: bool | None = None) -> None:
        named = sorted(e.name for e in d.effects)
        self.n += 1
        ok = named == sorted(self.hidden)
        self.exact += ok
        self.extra += bool(set(named) - set(self.hidden))
        self.misfit += bool(d.misfit)
        self.unexplained += bool(d.unexplained)
        self.any_named += bool(named)
        groups = [set(c.terms) for c in getattr(d, "confounded", [])]
        self.confounded += bool(groups)
        in_group = not named and any(set(self.hidden) <= g for g in groups)
        self.confounded_hidden += in_group
        if within is not None:
            self.within += within
            self.within_exact += within and ok
            self.within_confounded += within and in_group
            self.below_extra += not within and bool(set(named) - set(self.hidden))
        self.gains += [e.gain for e in d.effects if e.name in self.hidden]
        if not ok:
            where = {None: "", True: " [above the limit]", False: " [below the limit]"}[within]
            self.misses.append(
                f"{what}{where}: named {named or '-'}, confounded "
                f"{[sorted(g) for g in groups] or '-'}, partial "
                f"{[e.name for e in d.partial] or '-'}, negligible "
                f"{[e.name for e in d.negligible] or '-'}"
            )

    def pct(self, k: int) -> float:
        return 100.0 * k / max(self.n, 1)


def _within(limits: DetectionLimits | None, thetas: dict[str, np.ndarray]) -> bool | None:
    """Whether the one hidden effect is above the protocol's detection limit (None: no
    limits, or not exactly one hidden effect the steps excite)."""
    if limits is None or len(thetas) != 1:
        return None
    ((name, theta),) = thetas.items()
    return limits.above(name, theta)


def run_scenario(
    step_means_of: StepMeansOf,
    steps: pd.DataFrame,
    n_units: int,
    seed: int,
    hidden: tuple[str, ...] = (),
    scale: float = 1.0,
    out_of_catalogue: str | None = None,
    alpha: float = 0.01,
    limits: DetectionLimits | None = None,
) -> Tally:
    """Diagnose ``n_units`` physics-simulated units with the catalogue effects ``hidden``
    (or the physical error ``out_of_catalogue``) at ``scale`` times a realistic size.

    With ``limits`` (:func:`calib_core.discovery.detection.detection_limits` of ``steps``)
    and one hidden effect, each unit is also counted against the protocol's limit: whether
    its effect, as hidden, is detected with the limits' power and its expected held-out gain
    reaches min_gain (``Tally.within``): what discovery can be asked to name on that unit."""
    import time

    rng = np.random.default_rng(seed)
    tally = Tally(tuple(hidden))
    for u in range(n_units):
        unit = typical_physics_unit(rng)
        what, table, thetas = [], {}, {}
        for name in hidden:
            unit, theta, w = get_effect(name).hide(unit, rng, scale)
            thetas[name] = theta
            table.update(get_effect(name).table_knobs(theta))  # where the table stands
            what.append(f"{name} on {w}")
        if out_of_catalogue is not None:
            unit, w = OUT_OF_CATALOGUE[out_of_catalogue](unit, rng, scale)
            what.append(w)
        sessions = (
            step_means_of(unit, steps, rng, f"U{u:03d}", table=Turntable(**table))
            if table
            else step_means_of(unit, steps, rng, f"U{u:03d}")
        )
        t0 = time.perf_counter()
        d = diagnose_unit(sessions, alpha=alpha, tables=False)
        tally.seconds += time.perf_counter() - t0
        tally.add(d, f"unit {u} ({'; '.join(what) or 'clean'})", _within(limits, thetas))
    return tally
