"""The acceptance figures of the calibration over temperature (docs/thermal.md).

    PYTHONPATH=. python benchmarks/thermal_figures.py [UNITS] [SEED] [MC_RUNS] [SWEEPS]

defaults 40 units, seed 34, 30 Monte Carlo runs, 2 sweeps (MC_RUNS 0: no Monte Carlo).
Physics-simulated chamber runs (7 setpoints -40..85 degC, heating and cooling sweeps
alternately: one repetition of each setpoint per sweep); a quarter of the units each
linear, linear with hysteresis, cubic, cubic with hysteresis. Prints:

- the share of the thermal coefficients within 3 standard errors of the truth (the truth of
  the chosen polynomial: the true parameter curve projected on the fit's own design and
  weights, from the sensor settings by :func:`calib_core.sim.chamber.true_parameters`);
- the share of the six biases whose order is chosen right (1 on linear units, 3 on cubic
  ones), and of the K diagonals (1 or 2 on linear units: the inverse of a scale factor linear
  in temperature is curved; 3 on cubic ones);
- hysteresis named where present and where absent;
- Monte Carlo: one unit's chamber run repeated, mean standard error / sd of the estimates;
- compensation errors of held-out sessions between the setpoints (-30, 10, 75 degC), thermal
  calibration against a single-temperature calibration made at the 20 degC setpoint: the
  largest error on rate steps (xu2016 Table 3's measure), on static steps (gyro) and on
  static steps (accelerometer); as simulated (the session's own turn-on bias included) and
  with the session's repeatability noise (turn-on, instability) left out.
"""

from __future__ import annotations

import sys
import time
from dataclasses import dataclass, replace

import numpy as np

from calib_core.calibration import Calibration
from calib_core.models.thermal import BIASES, ThermalFit, calibrate_chamber
from calib_core.sim.chamber import chamber_schedule, thermal_physics_unit, true_parameters
from calib_core.sim.physics import PhysicsUnit
from calib_core.steps import StepMeans
from flows.chamber_sim import chamber_step_means, held_out_session

ORDERED = (
    "k_g11",
    "k_g22",
    "k_g33",
    "w0_x",
    "w0_y",
    "w0_z",
    "k_a11",
    "k_a22",
    "k_a33",
    "f0_x",
    "f0_y",
    "f0_z",
)
GAINS = ("k_g11", "k_g22", "k_g33", "k_a11", "k_a22", "k_a33")
HELD_OUT_C = (-30.0, 10.0, 75.0)
SINGLE_SETPOINT_C = 20.0


def truth_coefficients(unit: PhysicsUnit, fit: ThermalFit, name: str) -> np.ndarray:
    """The true curve of ``name`` at the fit's points projected on the fit's own design."""
    p = fit.params[name]
    T = np.array([q.temp_c for q in fit.points])
    d = np.array([q.sweep for q in fit.points], float)
    y = np.array([true_parameters(unit, t, s)[name] for t, s in zip(T, d)])
    X = p.design(T, d)
    s = np.sqrt(p.weights)
    return np.linalg.lstsq(X * s[:, None], y * s, rcond=None)[0][: p.order + 1]


def single_temperature(fit: ThermalFit, setpoint_c: float = SINGLE_SETPOINT_C) -> Calibration:
    """The calibration made at one setpoint: its sessions' xu2016 fits averaged."""
    pts = [q for q in fit.points if q.setpoint_c == setpoint_c]
    v = {n: np.mean([q.values[n] for q in pts]) for n in pts[0].values}
    mat = lambda s: np.array([[v[f"{s}{i}{j}"] for j in (1, 2, 3)] for i in (1, 2, 3)])  # noqa: E731
    return Calibration(
        mat("k_g"),
        np.array([v[f"w0_{a}"] for a in "xyz"]),
        mat("k_a"),
        np.array([v[f"f0_{a}"] for a in "xyz"]),
    )


def thermal_calibration(fit: ThermalFit) -> Calibration:
    ref = fit.at_reference()
    return Calibration(
        ref["K_g"], ref["w0"], ref["K_a"], ref["f0"], kind="thermal", thermal=fit.thermal_model()
    )


def compensation(sm: StepMeans, cal: Calibration) -> np.ndarray:
    """(rate, static gyro, accel): the largest |error| over rate steps, static steps."""
    w, f = cal.apply(sm.gyro, sm.accel, temp_c=sm.temp_c)
    rate = (sm.test == "multirate") & (sm.rate_dps != 0)
    static = sm.rate_dps == 0
    return np.array(
        [
            np.abs(w[rate] - sm.w_ref[rate]).max(),
            np.abs(w[static] - sm.w_ref[static]).max(),
            np.abs(f[static] - sm.f_ref[static]).max(),
        ]
    )


def without_turn_on(unit: PhysicsUnit) -> PhysicsUnit:
    """The unit without its turn-on bias (the bias drawn anew at each power-on: run-to-run
    repeatability, the same offset for every calibration applied to that session)."""
    gy = tuple(replace(g, turn_on=0.0) for g in unit.gyros)
    ac = tuple(replace(a, turn_on=0.0) for a in unit.accels)
    return replace(unit, gyros=gy, accels=ac)


def quiet(unit: PhysicsUnit) -> PhysicsUnit:
    """The unit without the noise a session repeats differently (turn-on, instability)."""
    gy = tuple(replace(g, turn_on=0.0, instability=0.0) for g in unit.gyros)
    ac = tuple(replace(a, turn_on=0.0, instability=0.0) for a in unit.accels)
    return replace(unit, gyros=gy, accels=ac)


# the held-out session as simulated, and the same session (same seed) without the parts of
# its bias no calibration can know: its turn-on bias, then also its in-run instability
VARIANTS = (
    ("as simulated", lambda u: u),
    ("its turn-on bias removed", without_turn_on),
    ("turn-on and in-run instability removed", quiet),
)


@dataclass
class UnitResult:
    kind: str
    within3: int
    n_coef: int
    order_right: int
    n_order: int
    gains_right: int
    n_gains: int
    hysteresis_present: bool
    hysteresis_named: bool
    ratios: np.ndarray  # (held-out temps, VARIANTS, 3 measures) single / thermal
    errors: np.ndarray  # (held-out temps, VARIANTS, 2 calibrations, 3 measures)


def evaluate_unit(
    rng: np.random.Generator, cubic: bool, hysteresis: bool, held_out=HELD_OUT_C, reps: int = 2
) -> UnitResult:
    """One unit's chamber run (``reps`` alternating sweeps), its thermal fit against the
    truth, and the held-out sessions' compensation errors."""
    unit = thermal_physics_unit(rng, cubic=cubic, hysteresis=hysteresis)
    fit = calibrate_chamber(chamber_step_means(unit, rng, chamber_schedule(reps=reps)))
    within = n = 0
    for name in fit.params:
        z = (fit.params[name].coef - truth_coefficients(unit, fit, name)) / fit.params[name].stderr
        within += int((np.abs(z) < 3).sum())
        n += len(z)
    want = 3 if cubic else 1
    right = sum(fit.params[nm].order == want for nm in BIASES)
    # the gains are the inverse of a scale factor linear in T on linear units: 1 / (1 + a dT)
    # has a curvature (a dT)^2 that the fits resolve (1e-5 at the ends on the z gyro), so
    # on linear units the gains count right at order 1 or 2, on cubic ones at 3
    gains_right = sum(
        (fit.params[nm].order == 3) if cubic else (fit.params[nm].order in (1, 2)) for nm in GAINS
    )
    therm, single = thermal_calibration(fit), single_temperature(fit)
    errors = np.zeros((len(held_out), len(VARIANTS), 2, 3))
    for i, t in enumerate(held_out):
        seed = int(rng.integers(2**63))
        for v, (_, variant) in enumerate(VARIANTS):
            sm = held_out_session(variant(unit), np.random.default_rng(seed), t)
            errors[i, v, 0] = compensation(sm, therm)
            errors[i, v, 1] = compensation(sm, single)
    kind = ("cubic" if cubic else "linear") + (" + hysteresis" if hysteresis else "")
    return UnitResult(
        kind,
        within,
        n,
        right,
        len(BIASES),
        gains_right,
        len(GAINS),
        hysteresis,
        bool(fit.hysteresis_named),
        errors[:, :, 1] / errors[:, :, 0],
        errors,
    )


def population(
    n_units: int = 40, seed: int = 34, held_out=HELD_OUT_C, log=None, reps: int = 2
) -> list[UnitResult]:
    rng = np.random.default_rng(seed)
    out = []
    for k in range(n_units):
        cubic, hysteresis = bool(k % 4 >= 2), bool(k % 2)
        out.append(evaluate_unit(rng, cubic, hysteresis, held_out, reps))
        if log:
            r = out[-1]
            log(
                f"  unit {k + 1:2d} {r.kind:22s} within 3 SE {r.within3}/{r.n_coef}"
                f"  order {r.order_right}/{r.n_order}"
                f"  hysteresis named {r.hysteresis_named}"
            )
    return out


def monte_carlo(runs: int = 30, seed: int = 34) -> dict[str, float]:
    """One cubic unit's chamber run repeated ``runs`` times (new noise each): the ratio of
    the mean standard error to the standard deviation of the estimates, per coefficient of
    the biases and K diagonals at the order the truth has (3), median over coefficients."""
    rng = np.random.default_rng(seed)
    unit = thermal_physics_unit(rng, cubic=True)
    coef, se = {}, {}
    for _ in range(runs):
        fit = calibrate_chamber(chamber_step_means(unit, rng))
        for nm in ORDERED:
            p = fit.params[nm]
            if p.order == 3:
                coef.setdefault(nm, []).append(p.coef)
                se.setdefault(nm, []).append(p.stderr)
    ratios = []
    for nm in coef:
        if len(coef[nm]) >= max(3, runs // 2):
            c, s = np.array(coef[nm]), np.array(se[nm])
            ratios.extend(s.mean(axis=0) / c.std(axis=0, ddof=1))
    r = np.array(ratios)
    return {
        "median": float(np.median(r)),
        "p10": float(np.percentile(r, 10)),
        "p90": float(np.percentile(r, 90)),
        "n": len(r),
    }


def main(argv: list[str]) -> None:
    n_units = int(argv[0]) if argv else 40
    seed = int(argv[1]) if len(argv) > 1 else 34
    runs = int(argv[2]) if len(argv) > 2 else 30
    reps = int(argv[3]) if len(argv) > 3 else 2
    t0 = time.time()
    res = population(n_units, seed, log=print, reps=reps)
    within = sum(r.within3 for r in res) / sum(r.n_coef for r in res)
    order = sum(r.order_right for r in res) / sum(r.n_order for r in res)
    pres = [r for r in res if r.hysteresis_present]
    absent = [r for r in res if not r.hysteresis_present]
    print(f"\n{n_units} units, seed {seed}, {reps} sweeps (repetitions per setpoint)")
    print(f"coefficients within 3 SE of the truth: {100 * within:.1f} % of {sum(r.n_coef for r in res)}")
    for kind in sorted({r.kind for r in res}):
        rs = [r for r in res if r.kind == kind]
        print(
            f"  {kind:22s} within 3 SE {100 * sum(r.within3 for r in rs) / sum(r.n_coef for r in rs):.1f} %"
            f"  order right {100 * sum(r.order_right for r in rs) / sum(r.n_order for r in rs):.1f} %"
        )
    print(
        f"order chosen right (1 linear / 3 cubic, the six biases): {100 * order:.1f} % "
        f"of {sum(r.n_order for r in res)}"
    )
    gains = sum(r.gains_right for r in res) / sum(r.n_gains for r in res)
    print(
        f"order of the K diagonals (1-2 linear / 3 cubic): {100 * gains:.1f} % "
        f"of {sum(r.n_gains for r in res)}"
    )
    print(
        f"hysteresis named where present: {sum(r.hysteresis_named for r in pres)}/{len(pres)}; "
        f"where absent: {sum(r.hysteresis_named for r in absent)}/{len(absent)}"
    )
    names = ("rate steps", "static gyro", "static accel")
    for group, rs in (("units without hysteresis", absent), ("units with hysteresis", pres)):
        if not rs:
            continue
        ratios = np.array([r.ratios for r in rs])  # (units, temps, variants, measures)
        errors = np.array([r.errors for r in rs])
        for v, (label, _) in enumerate(VARIANTS):
            print(
                f"compensation error, single (20 degC) / thermal, median over {len(rs)} {group} "
                f"(share of units >= 10x), held-out session {label}:"
            )
            for i, t in enumerate(HELD_OUT_C):
                cells = "  ".join(
                    f"{nm} {np.median(ratios[:, i, v, m]):.1f}x ({np.mean(ratios[:, i, v, m] >= 10):.0%}; "
                    f"{1e3 * np.median(errors[:, i, v, 0, m]):.3g} vs "
                    f"{1e3 * np.median(errors[:, i, v, 1, m]):.3g} m{'deg/s' if m < 2 else 'g'})"
                    for m, nm in enumerate(names)
                )
                print(f"  {t:+.0f} degC: {cells}")
    if runs < 2:
        print(f"({time.time() - t0:.0f} s)")
        return
    mc = monte_carlo(runs, seed)
    print(
        f"Monte Carlo ({runs} runs of one cubic unit): mean SE / sd of the estimates, median "
        f"{mc['median']:.2f} (10-90 %: {mc['p10']:.2f}-{mc['p90']:.2f}, {mc['n']} coefficients)"
    )
    print(f"({time.time() - t0:.0f} s)")


if __name__ == "__main__":
    main(sys.argv[1:])
