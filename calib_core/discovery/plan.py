"""What a protocol can identify, before anyone runs the turntable: every catalogue term's
columns on the protocol's steps (nominal unit, nominal noise) analysed by
:mod:`calib_core.discovery.identifiability`, and the step sets of the library
(:data:`calib_core.sim.protocols.STEP_SETS`) that would resolve each confounded or undetermined
set. ``mimucal plan`` prints it; model discovery asks it for a unit's own steps.

Assumptions, stated because the steps table alone does not say them:

- noise of a step mean: 0.01 deg/s per gyro channel, 0.1 mg per accelerometer channel (a
  MEMS unit averaged over a few seconds, bias instability included); only the ratio of the
  two matters (the terms are compared within a channel);
- time: steps follow each other, each lasting its ``duration_s`` (3 s without it; the
  settling time is part of it, averaging starts after it); the temperature follows a 10 degC
  warm-up with a 600 s time constant from
  power-on (the physics simulator's default), unless the frame carries ``t_mid``/``temp_c``;
- the base model is each channel's affine calibration (three gains and a bias).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np
import pandas as pd

from calib_core.discovery.identifiability import (
    DEFAULT_TOL,
    NEAR_TOL,
    Advice,
    Confounded,
    Identifiability,
    analyse,
    near_confounded,
    orthonormal_basis,
)
from calib_core.effects import MotionContext, catalogue, get_effect

NOMINAL_SIGMA = np.array([0.01, 0.01, 0.01, 1e-4, 1e-4, 1e-4])  # deg/s, g per step mean
WARM_UP_C = (25.0, 10.0, 600.0)  # start, rise, time constant (s)
DEFAULT_DURATION_S = 3.0


def step_context(
    steps: pd.DataFrame, latitude_deg: float | None = None, table_heading_deg: float | None = None
) -> MotionContext:
    """The motion of each step of a steps table (contract columns; optional ``duration_s``,
    ``heading_deg``, ``t_mid``, ``temp_c``), times and temperatures filled as the module
    docstring says."""
    n = len(steps)
    w = steps[["w_ref_x", "w_ref_y", "w_ref_z"]].to_numpy(float)
    f = steps[["f_ref_x", "f_ref_y", "f_ref_z"]].to_numpy(float)
    dur = steps["duration_s"].to_numpy(float) if "duration_s" in steps else np.full(n, DEFAULT_DURATION_S)
    dur = np.where(np.isfinite(dur), dur, DEFAULT_DURATION_S)
    settle = steps["settle_s"].to_numpy(float) if "settle_s" in steps else np.zeros(n)
    t_nominal = np.cumsum(dur) - (dur - settle) / 2.0
    t = steps["t_mid"].to_numpy(float) if "t_mid" in steps else np.full(n, np.nan)
    known = np.isfinite(t)
    if known.any() and not known.all():  # steps appended to a unit's: after its last step
        last = np.flatnonzero(known)[-1]
        t = np.where(known, t, t[last] + t_nominal - t_nominal[last])
    elif not known.any():
        t = t_nominal
    start, rise, tau = WARM_UP_C
    temp = steps["temp_c"].to_numpy(float) if "temp_c" in steps else np.full(n, np.nan)
    temp = np.where(np.isfinite(temp), temp, start + rise * (1.0 - np.exp(-t / tau)))
    heading = steps["heading_deg"].to_numpy(float) if "heading_deg" in steps else None
    # angle turned since the step's start at the averaged window's start and end (the
    # orientation convention, as StepMeans.turned_deg): given, or from settle and duration
    rate = np.linalg.norm(w, axis=1)
    turned = np.column_stack([0.75 * settle * rate, (0.75 * settle + np.maximum(dur - settle, 0.0)) * rate])
    if {"turned0_deg", "turned1_deg"} <= set(steps.columns):
        given = steps[["turned0_deg", "turned1_deg"]].to_numpy(float)
        turned = np.where(np.isfinite(given), given, turned)
    return MotionContext.from_refs(
        w,
        f,
        temp_c=temp,
        t=t,
        heading_deg=heading,
        latitude_deg=latitude_deg,
        table_heading_deg=table_heading_deg,
        turned_deg=turned,
    )


def design(
    steps: pd.DataFrame,
    names: list[str] | None = None,
    latitude_deg: float | None = None,
    table_heading_deg: float | None = None,
) -> tuple[np.ndarray, dict[str, np.ndarray], dict[str, tuple[str, ...]]]:
    """Weighted base columns (6 n, 24) and each term's columns (6 n, p): rows are the six
    channels of every step, each channel with its own affine base block."""
    ctx = step_context(steps, latitude_deg, table_heading_deg)
    n = len(ctx)
    names = sorted(catalogue()) if names is None else names
    base = np.zeros((6 * n, 24))
    for c in range(6):
        ref = ctx.w if c < 3 else ctx.f
        rows = slice(c * n, (c + 1) * n)
        base[rows, 4 * c : 4 * c + 3] = ref / NOMINAL_SIGMA[c]
        base[rows, 4 * c + 3] = 1.0 / NOMINAL_SIGMA[c]
    terms, pnames = {}, {}
    for nm in names:
        term = get_effect(nm)
        E = term.regressors(ctx)  # (n, 6, p)
        Z = (E / NOMINAL_SIGMA[None, :, None]).transpose(1, 0, 2).reshape(6 * n, -1)
        live = _excited(Z)
        if live.any():  # a parameter no step excites is not a question of the design
            terms[nm] = Z[:, live]
            pnames[nm] = tuple(p for p, ok in zip(term.param_names, live) if ok)
    # every question here is about angles and lengths of columns: the R factor of all the
    # columns together answers them with (24 + P) rows instead of 6 n
    names_live = list(terms)
    widths = [terms[nm].shape[1] for nm in names_live]
    Rf = np.linalg.qr(np.hstack([base] + [terms[nm] for nm in names_live]), mode="r")
    base_r = Rf[:, :24]
    out, at = {}, 24
    for nm, k in zip(names_live, widths):
        out[nm] = Rf[:, at : at + k]
        at += k
    return base_r, out, pnames


def _excited(Z: np.ndarray) -> np.ndarray:
    """Columns of a term that some step excites: above 1e-9 of the term's largest (a
    horizontal Earth rate averaged over whole turns is zero up to rounding)."""
    norms = np.linalg.norm(Z, axis=0)
    return norms > 1e-9 * max(norms.max(initial=0.0), 1e-300)


def not_excited(
    steps: pd.DataFrame, latitude_deg: float | None = None, table_heading_deg: float | None = None
) -> dict[str, tuple[str, ...]]:
    """Parameters no step excites at all, per term (e.g. temperature terms without a
    temperature change)."""
    ctx = step_context(steps, latitude_deg, table_heading_deg)
    out = {}
    for nm in sorted(catalogue()):
        term = get_effect(nm)
        E = term.regressors(ctx)
        dead = ~_excited((E / NOMINAL_SIGMA[None, :, None]).reshape(-1, E.shape[-1]))
        if dead.any():
            out[nm] = tuple(p for p, d in zip(term.param_names, dead) if d)
    return out


def analyse_steps(
    steps: pd.DataFrame,
    tol: float = DEFAULT_TOL,
    latitude_deg: float | None = None,
    table_heading_deg: float | None = None,
) -> Identifiability:
    base, terms, pnames = design(steps, latitude_deg=latitude_deg, table_heading_deg=table_heading_deg)
    return analyse(base, terms, pnames, tol)


def own_directions(
    base: np.ndarray,
    terms: Mapping[str, np.ndarray],
    term: str,
    others: tuple[str, ...],
    tol: float = DEFAULT_TOL,
) -> int:
    """Directions of ``term``'s columns that neither the base model nor ``others`` explain
    (the part left above ``tol``): what a test of ``term`` given the others can see."""
    Q = orthonormal_basis(np.hstack([base] + [terms[o] for o in others if o in terms]))
    if term not in terms:
        return 0
    Z = terms[term]
    Zn = Z / np.where(np.linalg.norm(Z, axis=0) > 0, np.linalg.norm(Z, axis=0), 1.0)
    s = np.linalg.svd(Zn - Q @ (Q.T @ Zn), compute_uv=False)
    s_all = np.linalg.svd(Zn, compute_uv=False)
    return int(np.sum(s > tol * max(s_all.max(initial=0.0), 1e-300)))


def separable(
    base: np.ndarray, terms: Mapping[str, np.ndarray], members: tuple[str, ...], tol: float = DEFAULT_TOL
) -> bool:
    """Every member of a confounded set has a direction of its own given the others."""
    return all(own_directions(base, terms, m, tuple(x for x in members if x != m), tol) > 0 for m in members)


def near_pairs(
    base: np.ndarray,
    terms: Mapping[str, np.ndarray],
    tol: float = DEFAULT_TOL,
    confounded: tuple[Confounded, ...] = (),
) -> tuple[Confounded, ...]:
    """Near-collinear pairs of terms (:func:`calib_core.discovery.identifiability.near_confounded`)
    once the base model is projected out of their columns; pairs inside a ``confounded``
    set are that set's business, not listed."""
    Q = orthonormal_basis(base)
    pairs = near_confounded({n: Z - Q @ (Q.T @ Z) for n, Z in terms.items()}, tol)
    return tuple(c for c in pairs if not any(set(c.terms) <= set(g.terms) for g in confounded))


SOAK_AFTER_S = 3600.0  # a temperature soak: the unit has settled an hour after power-on
CURVED_TAU_S = 150.0  # a warm-up whose time constant is well inside the session


def _with_temperature(steps: pd.DataFrame, tau_s: float, extra: pd.DataFrame | None = None) -> pd.DataFrame:
    """``steps`` (plus ``extra`` rows, whose ``t_mid`` is given) with explicit ``t_mid`` and
    ``temp_c``: the nominal times, a 10 degC warm-up with time constant ``tau_s``."""
    out = steps.copy()
    out["t_mid"] = step_context(steps).t
    if extra is not None:
        from calib_core.sim.protocols import extended

        out = extended(out, extra.to_dict("records"))
    start, rise, _ = WARM_UP_C
    out["temp_c"] = start + rise * (1.0 - np.exp(-out["t_mid"].to_numpy(float) / tau_s))
    return out


def _curved_warm_up(steps: pd.DataFrame) -> pd.DataFrame:
    return _with_temperature(steps, CURVED_TAU_S)


def _soak(steps: pd.DataFrame) -> pd.DataFrame:
    # the protocol's own stationary steps (its first three without any) run again: no new
    # motion, only a new temperature at a new time
    still = steps[steps["test"] == "stationary"] if "test" in steps else steps.iloc[:0]
    rows = (still if len(still) else steps.iloc[:3]).drop(columns=["step"]).reset_index(drop=True)
    rows["t_mid"] = SOAK_AFTER_S + DEFAULT_DURATION_S * np.arange(len(rows))
    return _with_temperature(steps, WARM_UP_C[2], rows)


REPEAT_GAP_S = 60.0  # between two passes of the protocol run back to back


def _repeated_on_one_warm_up(steps: pd.DataFrame) -> pd.DataFrame:
    # the whole protocol again right after the first pass, on the same warm-up: the second
    # pass is warmer and warms more slowly, while time runs on at the same rate (what
    # repetitions run back to back after one power-on give)
    first = _with_temperature(steps, WARM_UP_C[2])
    rows = steps.drop(columns=["step"]).reset_index(drop=True)
    end = float(first["t_mid"].max()) + DEFAULT_DURATION_S
    rows["t_mid"] = end + REPEAT_GAP_S + first["t_mid"].to_numpy(float)
    return _with_temperature(steps, WARM_UP_C[2], rows)


# changes of *when* the steps run (the temperature they see), beside the step sets of
# :data:`calib_core.sim.protocols.STEP_SETS`: what tells a drift in temperature from one in time
TEMPERATURE_CHANGES = {
    "a warm-up that is not linear in time over the session (steps started while the "
    "temperature still rises fast, time constant about 150 s)": _curved_warm_up,
    "a temperature soak at a different time (the stationary steps repeated once the unit "
    "has settled, an hour after power-on)": _soak,
    "repetitions run back to back on one warm-up (the protocol again right after, each "
    "pass at its own temperature)": _repeated_on_one_warm_up,
}


def advise(
    steps: pd.DataFrame,
    library: Mapping | None = None,
    tol: float = DEFAULT_TOL,
    latitude_deg: float | None = None,
    table_heading_deg: float | None = None,
    ident: Identifiability | None = None,
) -> list[Advice]:
    """For each confounded set, each near-collinear pair (:func:`near_pairs`: discovery
    lets the data decide it) and each term with undetermined parameters, the step sets of
    ``library`` (default :data:`calib_core.sim.protocols.STEP_SETS`) that resolve it, or the
    changes of when the steps run of :data:`TEMPERATURE_CHANGES`. A
    confounded set is resolved when every member has a direction of its own given the
    others (discovery can then test each member given the rest; a shared direction, such as
    the vertical Earth rate and an isotropic g-sensitivity, may remain); an undetermined
    term when all its excited parameters are determined."""
    from calib_core.sim.protocols import STEP_SETS, extended

    lib = STEP_SETS if library is None else library
    kw = {"latitude_deg": latitude_deg, "table_heading_deg": table_heading_deg}
    ident = analyse_steps(steps, tol, **kw) if ident is None else ident
    base0, terms0, _ = design(steps, **kw)
    issues = [
        (c.describe(), c.terms, "confounded")
        for c in ident.confounded
        if not separable(base0, terms0, c.terms, tol)
    ]
    issues += [
        (f"near-{c.describe()}", c.terms, "near") for c in near_pairs(base0, terms0, tol, ident.confounded)
    ]
    for term in sorted({u.term for u in ident.undetermined}):
        params = sorted({p for u in ident.undetermined if u.term == term for p in u.params})
        issues.append((f"undetermined: {term} ({', '.join(params)})", (term,), "undetermined"))
    if not issues:
        return []
    resolved: dict[str, list[str]] = {text: [] for text, _, _ in issues}
    changes = {label: (lambda s, rows=rows: extended(s, rows())) for label, rows in lib.items()}
    changes.update(TEMPERATURE_CHANGES)
    for label, change in changes.items():
        base, terms, _ = design(change(steps), **kw)
        ext = near = None
        for text, members, kind in issues:
            if kind == "confounded":
                ok = separable(base, terms, members, tol)
            elif kind == "near":  # no longer near-collinear, nor confounded
                near = near_pairs(base, terms, tol) if near is None else near
                ok = separable(base, terms, members, tol) and members not in {c.terms for c in near}
            else:
                if ext is None:
                    ext = analyse(
                        base, terms, {n: tuple(map(str, range(z.shape[1]))) for n, z in terms.items()}, tol
                    )
                ok = members[0] in ext.rank and ext.rank[members[0]] == ext.n_params[members[0]]
            if ok:
                resolved[text].append(label)
    return [Advice(text, members, tuple(resolved[text])) for text, members, _ in issues]


@dataclass(frozen=True)
class Plan:
    """What a steps table can and cannot identify. ``separable``: confounded sets whose
    members each keep a direction of their own (discovery tests each given the others)."""

    n_steps: int
    identifiability: Identifiability
    not_excited: dict[str, tuple[str, ...]]
    advice: tuple[Advice, ...]
    separable: tuple[tuple[str, ...], ...] = ()
    near: tuple[Confounded, ...] = ()  # near-collinear pairs (sine from tol to NEAR_TOL)

    def identifiable(self) -> list[str]:
        ident = self.identifiability
        return [t for t in ident.terms if ident.identifiable(t) and t not in self.not_excited]

    def lines(self) -> list[str]:
        ident = self.identifiability
        out = [
            f"{self.n_steps} steps; base model: an affine calibration per channel; "
            f"confounded / undetermined below {ident.tol:g} (sine of angle, part left)"
        ]
        for t in sorted(set(ident.terms) | set(self.not_excited)):
            if t in self.not_excited and t not in ident.terms:
                out.append(f"  {t}: not excited ({', '.join(self.not_excited[t])})")
                continue
            rank, p = ident.rank[t], ident.n_params[t]
            state = "identifiable" if ident.identifiable(t) else "NOT identifiable"
            extra = f"; not excited: {', '.join(self.not_excited[t])}" if t in self.not_excited else ""
            out.append(f"  {t}: {state}, {rank} of {p} parameter directions determined{extra}")
        for c in ident.confounded:
            if c.terms in self.separable:
                out.append(
                    f"  {c.describe()}: they share a direction, but each has one of "
                    f"its own (discovery tests each given the others)"
                )
            else:
                out.append(f"  {c.describe()}: cannot be told apart")
        for c in self.near:
            out.append(
                f"  near-{c.describe()}: told apart only by an effect several times the noise "
                f"(below {NEAR_TOL:g}; discovery tests each given the other)"
            )
        for u in ident.undetermined:
            out.append(f"  undetermined: {u.describe()} ({100 * u.left:.1f} % left)")
        for a in self.advice:
            out.append(f"  to resolve {a.describe()}")
        return out


def plan(
    steps: pd.DataFrame,
    tol: float = DEFAULT_TOL,
    latitude_deg: float | None = None,
    table_heading_deg: float | None = None,
) -> Plan:
    ident = analyse_steps(steps, tol, latitude_deg, table_heading_deg)
    base, terms, _ = design(steps, latitude_deg=latitude_deg, table_heading_deg=table_heading_deg)
    return Plan(
        len(steps),
        ident,
        not_excited(steps, latitude_deg, table_heading_deg),
        tuple(advise(steps, None, tol, latitude_deg, table_heading_deg, ident)),
        tuple(c.terms for c in ident.confounded if separable(base, terms, c.terms, tol)),
        near_pairs(base, terms, tol, ident.confounded),
    )
