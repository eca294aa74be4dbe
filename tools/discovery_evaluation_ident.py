"""The Done-when figures of docs/model-discovery.md on confounding, the Earth rate and the
thermal terms, on the independent physics simulator (:mod:`calib_core.sim.physics`).

Each scenario diagnoses ``n_units`` simulated units and counts outcomes. Step means come
from a caller-given function ``step_means_of(unit, steps, rng, unit_id, table)`` (the
reader's averaging lives in ``schemas.physics_sessions``).

The Earth-rate scenarios use gyros whose bias instability (0.002 deg/s = 7 deg/h, white
noise 0.002 deg/s/sqrt(Hz)) is below the Earth rate: with the typical MEMS unit of
:func:`typical_physics_unit` (0.01 deg/s = 36 deg/h) the 10.6 deg/h vertical part at 45 deg
latitude is below what five repetitions can tell from the noise (see
:func:`earth_rate_scenario`'s ``quiet`` flag and the figures).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
import pandas as pd

from calib_core.discovery.turntable import diagnose_unit
from calib_core.effects import get_effect
from calib_core.effects.earth_rate import EARTH_RATE_DEG_H
from calib_core.sim.physics import PhysicsUnit, Turntable, WarmUp, typical_physics_unit

StepMeansOf = Callable[..., list]
DEG = np.pi / 180.0


def quiet_gyros(unit: PhysicsUnit) -> PhysicsUnit:
    """The unit with gyros of 7 deg/h bias instability (0.002 deg/s, white 0.002
    deg/s/sqrt(Hz), turn-on 0.02 deg/s): a gyro that can see the Earth's rotation."""
    for i in range(3):
        unit = unit.replace_gyro(i, instability=0.002, white_density=0.002, turn_on=0.02)
    return unit


@dataclass
class Outcome:
    """Counts of one scenario."""

    n: int = 0
    named_alone: int = 0  # the hidden effect named, nothing else named or confounded
    named: int = 0  # the hidden effect named (others beside it allowed)
    confounded: int = 0  # the hidden effect in a confounded group, nothing named alone
    confounded_set_aside: int = 0  # ... in a confounded group found negligible, nothing named
    other_named: int = 0  # some other catalogue effect named alone
    within_2se: int = 0  # estimate within 2 standard errors of the truth (when named)
    right_axis: int = 0
    notes: list[str] = field(default_factory=list)
    # per place the effect was hidden (its module's description, e.g. "sensor ay"):
    # [units, named with the right axis]
    by_place: dict[str, list[int]] = field(default_factory=dict)

    def pct(self, k: int) -> float:
        return 100.0 * k / max(self.n, 1)


def _tally(out: Outcome, d, hidden: str, check=None, what: str = "") -> None:
    named = [e.name for e in d.effects]
    groups = [set(c.terms) for c in d.confounded]
    out.n += 1
    out.named += hidden in named
    out.named_alone += named == [hidden] and not groups
    out.confounded += bool(not named and any(hidden in g for g in groups))
    out.confounded_set_aside += bool(
        not named and not groups and any(hidden in g for g in getattr(d, "confounded_set_aside", []))
    )
    out.other_named += bool(set(named) - {hidden})
    place = out.by_place.setdefault(what.partition("(")[2].rstrip(")"), [0, 0])
    place[0] += 1
    if hidden in named and check is not None:
        ok_est, ok_axis = check(next(e for e in d.effects if e.name == hidden))
        out.within_2se += ok_est
        out.right_axis += ok_axis
        place[1] += ok_axis
    if not (named == [hidden] and not groups):
        out.notes.append(f"{what}: named {named or '-'}, confounded {[sorted(g) for g in groups] or '-'}")


def earth_rate_scenario(
    step_means_of: StepMeansOf,
    steps: pd.DataFrame,
    n_units: int,
    seed: int,
    latitude_deg: float = 45.0,
    declare: bool = False,
    quiet: bool = True,
) -> Outcome:
    """Units with the Earth's rotation at ``latitude_deg`` (random table heading); with
    ``declare`` the samples carry latitude_deg/table_heading_deg. The estimate is checked
    against 15.041 sin(latitude) deg/h (omega_up)."""
    rng = np.random.default_rng(seed)
    truth = EARTH_RATE_DEG_H * np.sin(latitude_deg * DEG)
    out = Outcome()

    def check(e):
        v, se = e.estimate["omega_up"], e.stderr["omega_up"]
        return bool(v is not None and se and abs(v - truth) <= 2 * se), True

    for u in range(n_units):
        unit = typical_physics_unit(rng)
        if quiet:
            unit = quiet_gyros(unit)
        table = Turntable(
            latitude_deg=latitude_deg, heading_deg=float(rng.uniform(0, 360)), declare_location=declare
        )
        d = diagnose_unit(step_means_of(unit, steps, rng, f"E{u:03d}", table), tables=False)
        _tally(out, d, "earth_rate", check, f"unit {u}")
    return out


def sensor_effect_scenario(
    step_means_of: StepMeansOf,
    steps: pd.DataFrame,
    name: str,
    n_units: int,
    seed: int,
    scale: float = 1.0,
    warm_up: WarmUp | None = None,
) -> Outcome:
    """Units with the catalogue effect ``name`` hidden by its module at ``scale`` (and the
    temperature ``warm_up``, default :class:`WarmUp`); the "right axis" is the sensor of
    its largest hidden parameter being the sensor of the estimate's largest |t|."""
    rng = np.random.default_rng(seed)
    term = get_effect(name)
    out = Outcome()
    for u in range(n_units):
        unit = typical_physics_unit(rng, temperature=WarmUp() if warm_up is None else warm_up)
        unit, theta, what = term.hide(unit, rng, scale)
        hidden_param = term.param_names[int(np.argmax(np.abs(theta)))]

        def check(e, hidden_param=hidden_param, theta=theta):
            t = {k: abs(v) / e.stderr[k] for k, v in e.estimate.items() if v is not None and e.stderr[k]}
            best = max(t, key=t.get) if t else None
            v, se = e.estimate.get(hidden_param), e.stderr.get(hidden_param)
            true = float(theta[term.param_names.index(hidden_param)])
            return bool(v is not None and se and abs(v - true) <= 2 * se), best == hidden_param

        d = diagnose_unit(step_means_of(unit, steps, rng, f"T{u:03d}", None), tables=False)
        _tally(out, d, name, check, f"unit {u} ({what})")
    return out


@dataclass
class PairOutcome:
    """Counts of a scenario with several effects hidden at once."""

    hidden: tuple[str, ...]
    n: int = 0
    named: int = 0  # exactly the hidden effects named, no confounded group
    found: int = 0  # every hidden effect named or in a confounded group; nothing else named
    confounded: int = 0  # ... of which with a hidden effect in a confounded group
    other_named: int = 0  # a catalogue effect named that was not hidden
    notes: list[str] = field(default_factory=list)

    def pct(self, k: int) -> float:
        return 100.0 * k / max(self.n, 1)


def pair_scenario(
    step_means_of: StepMeansOf,
    steps: pd.DataFrame,
    hidden: tuple[str, ...],
    n_units: int,
    seed: int,
    scale: float = 1.0,
    warm_up: WarmUp | None = None,
) -> PairOutcome:
    """Units with every effect of ``hidden`` hidden by its module at ``scale``, warm-up
    ``warm_up`` (default :class:`WarmUp`). "Found" counts a hidden effect reported in a
    confounded group (with a term it cannot be told from on these steps) as found: the
    group's combined fit is applied, and no wrong name is given."""
    rng = np.random.default_rng(seed)
    out = PairOutcome(tuple(hidden))
    for u in range(n_units):
        unit = typical_physics_unit(rng, temperature=WarmUp() if warm_up is None else warm_up)
        what = []
        for name in hidden:
            unit, _, w = get_effect(name).hide(unit, rng, scale)
            what.append(f"{name} on {w}")
        d = diagnose_unit(step_means_of(unit, steps, rng, f"P{u:03d}", None), tables=False)
        named = {e.name for e in d.effects}
        grouped = {n for c in d.confounded for n in c.terms}
        out.n += 1
        out.named += named == set(hidden) and not grouped
        ok = named <= set(hidden) and set(hidden) <= named | grouped
        out.found += ok
        out.confounded += ok and bool(grouped & set(hidden))
        out.other_named += bool(named - set(hidden))
        if not (named == set(hidden) and not grouped):
            out.notes.append(
                f"unit {u} ({'; '.join(what)}): named {sorted(named) or '-'}, confounded "
                f"{[list(c.terms) for c in d.confounded] or '-'}"
            )
    return out
