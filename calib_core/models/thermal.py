"""Calibration over temperature: a unit's chamber sessions -> its parameters as polynomials in
the sensor temperature (:class:`calib_core.thermal_model.ThermalModel`).

The method, in order:

1. **Soak.** A session is soaked when the mean temperatures of its steps (``temp_c``, the
   sensor's own) lie within ``SOAK_TOLERANCE_C`` of each other. A session that is not is
   named (``W_NOT_SOAKED``) and left out of the fit, never pooled with the soaked ones;
   past ``SOAK_LIMIT_C`` it is an error of that session (``E_NOT_SOAKED``). Fewer than
   ``MIN_SETPOINTS`` soaked setpoints: :class:`DesignError` ``E_THERMAL_UNDETERMINED``.
2. **Per setpoint.** Each soaked session is calibrated with the existing methods (xu2016's
   multirate gyro and multiposition accelerometer fits, by the caller, through
   :func:`calib_core.models.pipeline.calibrate_repetitions`): K_g, w0, K_a, f0 with standard
   errors, at the session's mean sensor temperature.
3. **Polynomials.** Each of the 24 parameters is fitted over the sessions by weighted least
   squares (:func:`calib_core.linalg.solve_lstsq`) in powers of ``T - T_REF_C``. The weights
   are ``1 / (se_i^2 + tau^2)``: ``se_i`` the session's own standard error, ``tau^2`` the
   scatter between sessions it does not see (turn-on biases), estimated from the residual of
   the most flexible model (cubic plus a heating/cooling offset). The standard errors scale
   with the residual of the chosen fit.
4. **Order.** Per parameter, 0 to 3, by held-out error across setpoints: each interior
   setpoint is left out in turn, the polynomial fitted on the others predicts it, and the
   order with the smallest weighted mean squared prediction error is kept unless a lower one
   is within ``ORDER_TOLERANCE`` of it (the extreme setpoints are never predicted: that would
   score extrapolation); a higher order whose top coefficient is under ``ORDER_T`` standard
   errors steps down (selection by held-out error alone takes noise for curvature on about
   one linear parameter in seven).
5. **Hysteresis.** With sessions reached by heating and by cooling, each bias (w0, f0) gets a
   heating-minus-cooling offset tested by its t statistic (Bonferroni over the six biases at
   ``HYSTERESIS_ALPHA`` for the unit). A named hysteresis stays in that parameter's fit (so its
   coefficients are those of the mid-line) and is reported; the applied model is the
   mid-line (the direction is unknown when the calibration is used).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np
import pandas as pd
from scipy import stats

from calib_core.errors import DesignError
from calib_core.linalg import solve_lstsq
from calib_core.results import Param
from calib_core.steps import StepMeans
from calib_core.thermal_model import (
    GYRO_NAMES,
    PARAM_NAMES,
    ThermalModel,
    coefficient_name,
    coefficient_unit,
)

T_REF_C = 25.0
SOAK_TOLERANCE_C = 0.5  # spread of a soaked session's step temperatures, degC
SOAK_LIMIT_C = 10.0  # past this spread the session is an error, not a warning
MIN_SETPOINTS = 3
MAX_ORDER = 3
ORDER_TOLERANCE = 0.10  # a lower order is kept when its held-out error is within 10 %
ORDER_T = 2.5  # ... or when the top coefficient of the higher one is under 2.5 standard errors
HYSTERESIS_ALPHA = 0.001  # the unit's chance of naming a hysteresis it does not have
BIASES = ("w0_x", "w0_y", "w0_z", "f0_x", "f0_y", "f0_z")
SWEEPS = {"heating": 1, "cooling": -1}
# the parameters the unit report draws against temperature (K diagonals and biases)
PLOTTED = (
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
ROBUST_Z = 3.5  # a unit's coefficient this many robust sd from the lot median is an outlier


@dataclass(frozen=True)
class Soak:
    """Whether one session was soaked: its step temperatures' spread and mean."""

    key: str
    setpoint_c: float
    mean_c: float
    spread_c: float
    soaked: bool

    @property
    def warning(self) -> str | None:
        if self.soaked:
            return None
        return (
            f"W_NOT_SOAKED: {self.key}: step temperatures span {self.spread_c:.2f} degC "
            f"(> {SOAK_TOLERANCE_C} degC) at setpoint {self.setpoint_c:g} degC; left out of the thermal fit"
        )


def soak_of(sm: StepMeans, setpoint_c: float, tolerance_c: float = SOAK_TOLERANCE_C) -> Soak:
    """The soak of one session from its steps' mean temperatures (the sensor's own)."""
    t = np.asarray(sm.temp_c, float)
    t = t[np.isfinite(t)]
    if len(t) == 0:
        raise DesignError("E_NO_TEMPERATURE", f"{sm.key}: no temp_c recorded; a chamber session needs it")
    spread = float(t.max() - t.min())
    if spread > SOAK_LIMIT_C:
        raise DesignError(
            "E_NOT_SOAKED",
            f"{sm.key}: step temperatures span {spread:.1f} degC (> {SOAK_LIMIT_C:g} degC) at "
            f"setpoint {setpoint_c:g} degC: not a chamber soak",
        )
    return Soak(str(sm.key), float(setpoint_c), float(t.mean()), spread, spread <= tolerance_c)


@dataclass(frozen=True)
class ChamberPoint:
    """One soaked session's calibration at its temperature: what the polynomials are fitted to."""

    key: str
    setpoint_c: float
    temp_c: float
    sweep: int  # +1 heating, -1 cooling, 0 unknown
    values: dict[str, float]
    stderr: dict[str, float]
    units: dict[str, str]


def chamber_point(key: str, setpoint_c: float, temp_c: float, sweep: int, fits: dict) -> ChamberPoint:
    """The K_g, w0, K_a, f0 of one session's xu2016 fits (``fits["gyro"]``, ``fits["accel"]``)."""
    values, se, units = {}, {}, {}
    for model in ("gyro", "accel"):
        for p in fits[model].parameters():
            values[p.name], se[p.name], units[p.name] = p.value, p.stderr, p.unit
    return ChamberPoint(key, float(setpoint_c), float(temp_c), int(sweep), values, se, units)


def infer_sweeps(setpoints: list[float], order: list[float]) -> list[int]:
    """Heating (+1) or cooling (-1) of sessions without a declared sweep, from their setpoints
    in acquisition order: the sign of the move from the previous session's setpoint; a
    session at the previous one's setpoint keeps its direction; the first takes the direction
    of the first move."""
    idx = np.argsort(order, kind="stable")
    sp = np.asarray(setpoints, float)[idx]
    d = np.sign(np.diff(sp))
    moves = d[d != 0]
    first = int(moves[0]) if len(moves) else 0
    out_sorted = [first]
    for k in range(1, len(sp)):
        out_sorted.append(int(d[k - 1]) if d[k - 1] != 0 else out_sorted[-1])
    out = [0] * len(sp)
    for pos, i in enumerate(idx):
        out[i] = out_sorted[pos]
    return out


@dataclass(frozen=True)
class ParamPolynomial:
    """One parameter over temperature: its coefficients (c0..c_order, per degC^k), their
    standard errors and covariance, the held-out error of each order, the hysteresis test."""

    name: str
    unit: str
    order: int
    coef: np.ndarray
    stderr: np.ndarray
    cov: np.ndarray
    dof: int
    heldout: np.ndarray  # (MAX_ORDER + 1,) weighted held-out mean squared error per order
    hysteresis: float  # heating minus cooling (nan without both sweeps)
    hysteresis_stderr: float
    hysteresis_p: float
    hysteresis_in_fit: bool
    weights: np.ndarray  # the weights of the points (what the truth of a test projects with)

    def design(self, temp_c: np.ndarray, sweep: np.ndarray) -> np.ndarray:
        """The fit's design matrix at these temperatures and sweeps."""
        return _design(temp_c, sweep, self.order, self.hysteresis_in_fit)


def _design(temp_c, sweep, order: int, hysteresis: bool) -> np.ndarray:
    dt = np.asarray(temp_c, float) - T_REF_C
    cols = [dt**k for k in range(order + 1)]
    if hysteresis:
        cols.append(0.5 * np.asarray(sweep, float))
    return np.column_stack(cols)


def _wls(X: np.ndarray, y: np.ndarray, w: np.ndarray):
    s = np.sqrt(w)
    return solve_lstsq(X * s[:, None], y * s)


def _heldout(T, d, y, w, setpoints, order: int) -> float:
    """Weighted mean squared error of predicting each interior setpoint's sessions from the
    others' polynomial of this order (no hysteresis column: its mid-line is what is applied)."""
    uniq = np.unique(setpoints)
    interior = uniq[1:-1]
    err, wt = 0.0, 0.0
    for s in interior:
        out = setpoints == s
        keep = ~out
        if len(np.unique(setpoints[keep])) <= order:
            return np.inf
        ls = _wls(_design(T[keep], d[keep], order, False), y[keep], w[keep])
        pred = _design(T[out], d[out], order, False) @ ls.coef
        err += float(np.sum(w[out] * (y[out] - pred) ** 2))
        wt += float(np.sum(w[out]))
    return err / wt if wt else np.inf


def fit_parameter(
    name: str, unit: str, T: np.ndarray, d: np.ndarray, y: np.ndarray, se: np.ndarray, setpoints: np.ndarray
) -> ParamPolynomial:
    """One parameter's polynomial (module docstring, steps 3-5)."""
    n_set = len(np.unique(setpoints))
    both = (d > 0).any() and (d < 0).any()
    top = min(MAX_ORDER, n_set - 1)
    # tau^2: the scatter between sessions their own standard errors do not see, from the
    # residual of the most flexible model
    flex = _design(T, d, top, both)
    if len(y) > flex.shape[1]:
        ls = solve_lstsq(flex, y)
        tau2 = max(0.0, float(np.ravel(ls.sigma2)[0]) - float(np.mean(se**2)))
    else:
        tau2 = 0.0
    w = 1.0 / (se**2 + tau2)
    w = w / w.mean()
    heldout = np.full(MAX_ORDER + 1, np.inf)
    for order in range(top + 1):
        heldout[order] = _heldout(T, d, y, w, setpoints, order)
    if np.isfinite(heldout).any():
        best = float(np.min(heldout))
        order = int(np.flatnonzero(heldout <= best * (1.0 + ORDER_TOLERANCE))[0])
    else:
        order = min(1, top)
    # a higher order is kept only when its top coefficient is significant too: the held-out
    # error of seven setpoints alone lets about one linear parameter in seven through as
    # curved (selection by chance)
    while order > 0:
        ls = _wls(_design(T, d, order, both), y, w)
        if abs(ls.coef[order]) >= ORDER_T * ls.stderr[order]:
            break
        order -= 1
    h = h_se = h_p = np.nan
    in_fit = False
    if both and len(y) > order + 2:
        ls = _wls(_design(T, d, order, True), y, w)
        h, h_se = float(ls.coef[-1]), float(ls.stderr[-1])
        h_p = float(2.0 * stats.t.sf(abs(h / h_se), ls.dof)) if h_se > 0 and ls.dof > 0 else np.nan
        in_fit = name in BIASES and bool(h_p < HYSTERESIS_ALPHA / len(BIASES))
    ls = _wls(_design(T, d, order, in_fit), y, w)
    k = order + 1
    cov = ls.cov_unscaled[:k, :k] * float(np.ravel(ls.sigma2)[0])
    return ParamPolynomial(
        name,
        unit,
        order,
        ls.coef[:k].copy(),
        ls.stderr[:k].copy(),
        cov,
        int(ls.dof),
        heldout,
        h,
        h_se,
        h_p,
        in_fit,
        w,
    )


@dataclass(frozen=True)
class ThermalFit:
    """A unit's calibration over temperature (``model = "thermal"``)."""

    params: dict[str, ParamPolynomial]
    points: tuple[ChamberPoint, ...]
    soaks: tuple[Soak, ...]
    setpoints: tuple[float, ...]
    t_min_c: float
    t_max_c: float
    warnings: tuple[str, ...] = ()
    model: str = "thermal"
    hysteresis_named: tuple[str, ...] = field(default=())

    def thermal_model(self) -> ThermalModel:
        return ThermalModel(
            T_REF_C,
            self.t_min_c,
            self.t_max_c,
            {n: p.coef.copy() for n, p in self.params.items()},
            {n: self.params[n].hysteresis for n in self.hysteresis_named},
        )

    def at_reference(self) -> dict[str, np.ndarray]:
        """K_g, w0, K_a, f0 at T_REF_C (the c0 coefficients)."""
        c0 = {n: p.coef[0] for n, p in self.params.items()}
        mat = lambda s: np.array([[c0[f"{s}{i}{j}"] for j in (1, 2, 3)] for i in (1, 2, 3)])  # noqa: E731
        return {
            "K_g": mat("k_g"),
            "w0": np.array([c0[f"w0_{a}"] for a in "xyz"]),
            "K_a": mat("k_a"),
            "f0": np.array([c0[f"f0_{a}"] for a in "xyz"]),
        }

    def parameters(self) -> list[Param]:
        """Every coefficient (``w0_tc_x``, ``k_g11_tc2``, ...) with its standard error and
        unit, the hysteresis offsets (``w0_hyst_x``), and each parameter's order."""
        out = []
        for n, p in self.params.items():
            for k in range(p.order + 1):
                out.append(
                    Param(
                        self.model,
                        coefficient_name(n, k),
                        float(p.coef[k]),
                        float(p.stderr[k]),
                        coefficient_unit(p.unit, k),
                    )
                )
            out.append(Param(self.model, f"{n}_order", float(p.order), float("nan"), ""))
            if n in BIASES and np.isfinite(p.hysteresis):
                hname = f"{n[:-2]}_hyst_{n[-1]}"
                out.append(Param(self.model, hname, p.hysteresis, p.hysteresis_stderr, p.unit))
        return out

    def to_dict(self) -> dict[str, Any]:
        return {
            "model": self.model,
            "t_ref_c": T_REF_C,
            "range_c": [self.t_min_c, self.t_max_c],
            "setpoints_c": list(self.setpoints),
            "orders": {n: p.order for n, p in self.params.items()},
            "hysteresis_named": list(self.hysteresis_named),
            "hysteresis": {
                n: {"value": p.hysteresis, "stderr": p.hysteresis_stderr, "p": p.hysteresis_p}
                for n, p in self.params.items()
                if n in BIASES
            },
            "sessions": [
                {
                    "session": s.key,
                    "setpoint_c": s.setpoint_c,
                    "temp_c": s.mean_c,
                    "spread_c": s.spread_c,
                    "soaked": s.soaked,
                }
                for s in self.soaks
            ],
            "warnings": list(self.warnings),
            "curves": self.curves(),
        }

    def curves(self, names=PLOTTED, n_grid: int = 41, level: float = 0.95) -> dict[str, Any]:
        """What the unit report draws per parameter: each session's estimate (temperature,
        value, standard error, sweep), the fitted mid-line on a grid over the calibrated
        range and its ``level`` confidence band (t quantile of the fit's dof); and the same
        relative to the fitted value at ``T_REF_C`` (``reference``, the c0 coefficient):
        ``change`` (points, fit, lo, hi), what a gain is drawn as (its change from 25 degC)."""
        grid = np.linspace(self.t_min_c, self.t_max_c, n_grid)
        out = {}
        for n in names:
            p = self.params[n]
            X = _design(grid, np.zeros_like(grid), p.order, False)
            fit = X @ p.coef
            half = stats.t.ppf(0.5 + level / 2, max(p.dof, 1)) * np.sqrt(
                np.maximum(np.einsum("ij,jk,ik->i", X, p.cov, X), 0.0)
            )
            values = np.array([q.values[n] for q in self.points], float)
            ref = float(p.coef[0])
            out[n] = {
                "unit": p.unit,
                "order": p.order,
                "points": {
                    "temp_c": [q.temp_c for q in self.points],
                    "value": values.tolist(),
                    "stderr": [q.stderr[n] for q in self.points],
                    "sweep": [q.sweep for q in self.points],
                },
                "grid_c": grid.tolist(),
                "fit": fit.tolist(),
                "lo": (fit - half).tolist(),
                "hi": (fit + half).tolist(),
                "level": level,
                "t_ref_c": T_REF_C,
                "reference": ref,
                "change": {
                    "value": (values - ref).tolist(),
                    "fit": (fit - ref).tolist(),
                    "lo": (fit - half - ref).tolist(),
                    "hi": (fit + half - ref).tolist(),
                },
            }
        return out


def fit_thermal(points: list[ChamberPoint], soaks: list[Soak] = (), warnings: list[str] = ()) -> ThermalFit:
    """The polynomials of every parameter from the soaked sessions' calibrations.

    Raises DesignError ``E_THERMAL_UNDETERMINED`` with fewer than ``MIN_SETPOINTS`` setpoints."""
    setpoints = np.array([p.setpoint_c for p in points], float)
    uniq = np.unique(setpoints)
    if len(uniq) < MIN_SETPOINTS:
        raise DesignError(
            "E_THERMAL_UNDETERMINED",
            f"{len(uniq)} soaked setpoint(s) ({', '.join(f'{s:g}' for s in uniq) or 'none'} degC); "
            f"a thermal calibration needs {MIN_SETPOINTS}",
        )
    T = np.array([p.temp_c for p in points], float)
    d = np.array([p.sweep for p in points], float)
    params = {}
    for name in PARAM_NAMES:
        y = np.array([p.values[name] for p in points], float)
        se = np.array([p.stderr[name] for p in points], float)
        se = np.where(np.isfinite(se) & (se > 0), se, np.nanmedian(se[se > 0]) if (se > 0).any() else 1.0)
        params[name] = fit_parameter(name, points[0].units[name], T, d, y, se, setpoints)
    named = tuple(n for n in BIASES if params[n].hysteresis_in_fit)
    out_warnings = list(warnings)
    if named:
        out_warnings.append(
            "W_THERMAL_HYSTERESIS: heating and cooling differ in "
            + ", ".join(f"{n} by {params[n].hysteresis:+.3g} {params[n].unit}" for n in named)
        )
    return ThermalFit(
        params,
        tuple(points),
        tuple(soaks),
        tuple(float(s) for s in uniq),
        float(T.min()),
        float(T.max()),
        tuple(out_warnings),
        hysteresis_named=named,
    )


def gyro_or_accel(name: str) -> str:
    return "gyro" if name in GYRO_NAMES else "accel"


@dataclass(frozen=True)
class ChamberSessionInput:
    """A session of a chamber run as the caller read it: its step means, the setpoint of its
    metadata (``chamber_setpoint_c``), its sweep (+1 heating, -1 cooling, 0 unknown)."""

    sm: StepMeans
    setpoint_c: float
    sweep: int = 0


def calibrate_chamber(sessions: list[ChamberSessionInput]) -> ThermalFit:
    """Soak check, per-session calibration by the existing methods, polynomials (module
    docstring). A session that is not soaked or whose calibration fails is named in the
    warnings and left out; DesignError ``E_THERMAL_UNDETERMINED`` when fewer than
    ``MIN_SETPOINTS`` setpoints remain."""
    from calib_core.models.pipeline import calibrate_repetitions

    warnings: list[str] = []
    soaks: list[Soak] = []
    kept: list[ChamberSessionInput] = []
    for s in sessions:
        try:
            soak = soak_of(s.sm, s.setpoint_c)
        except DesignError as exc:
            warnings.append(f"{exc.code}: {exc.reason}")
            continue
        soaks.append(soak)
        if soak.soaked:
            kept.append(s)
        else:
            warnings.append(soak.warning)
    fits = calibrate_repetitions([s.sm for s in kept])
    points = []
    mean_t = {sk.key: sk.mean_c for sk in soaks}
    for s, fit in zip(kept, fits):
        if isinstance(fit, Exception):
            warnings.append(f"W_THERMAL_SESSION_FAILED: {s.sm.key}: {fit}")
            continue
        points.append(
            chamber_point(str(s.sm.key), s.setpoint_c, mean_t[str(s.sm.key)], s.sweep, fit.calibration.fits)
        )
    return fit_thermal(points, soaks, warnings)


def coefficient_spread(rows: pd.DataFrame) -> pd.DataFrame:
    """The spread over a lot of each thermal coefficient: ``rows`` has one row per unit and
    coefficient (``unit``, ``parameter``, ``value``, ``unit_of_measure``, ``flagged``).
    Returns per coefficient: n, median, robust sd (1.4826 MAD), min, max, and ``outliers``:
    the units more than ``ROBUST_Z`` robust sd from the median, or flagged (limits)."""
    out = []
    for name, g in rows.groupby("parameter", sort=False):
        v = g["value"].to_numpy(float)
        ok = np.isfinite(v)
        if not ok.any():
            continue
        med = float(np.median(v[ok]))
        rsd = float(1.4826 * np.median(np.abs(v[ok] - med)))
        z = np.where(ok, (v - med) / rsd, 0.0) if rsd > 0 else np.zeros_like(v)
        flagged = g["flagged"].fillna(False).to_numpy(bool) if "flagged" in g else np.zeros(len(g), bool)
        units = g["unit"].astype(str).to_numpy()
        outl = [
            f"{u} ({'limit' if f else f'z {zz:+.1f}'})"
            for u, zz, f in zip(units, z, flagged)
            if f or abs(zz) > ROBUST_Z
        ]
        out.append(
            {
                "parameter": name,
                "unit_of_measure": str(g["unit_of_measure"].iloc[0]) if "unit_of_measure" in g else "",
                "n": int(ok.sum()),
                "median": med,
                "robust_sd": rsd,
                "min": float(v[ok].min()),
                "max": float(v[ok].max()),
                "outliers": outl,
            }
        )
    return pd.DataFrame(out)


def lot_spread_records(summary: pd.DataFrame) -> list[dict[str, Any]]:
    """:func:`coefficient_spread` of a lot's stored summary rows of the model ``thermal``
    (the temperature coefficients ``*_tc*``; ``mean`` is a unit's value, ``flagged`` its
    limit or outlier flag), as JSON-ready records (what the lot report shows); [] without
    thermal rows."""
    if summary is None or not len(summary) or "model" not in summary:
        return []
    rows = summary[(summary["model"] == "thermal") & summary["parameter"].astype(str).str.contains("_tc")]
    if not len(rows):
        return []
    spread = coefficient_spread(
        pd.DataFrame(
            {
                "unit": rows["unit"].astype(str),
                "parameter": rows["parameter"].astype(str),
                "value": rows["mean"].astype(float),
                "unit_of_measure": rows["unit_of_measure"] if "unit_of_measure" in rows else "",
                "flagged": rows["flagged"] if "flagged" in rows else False,
            }
        )
    )
    return [
        {k: (list(v) if k == "outliers" else v) for k, v in r.items()}
        for r in spread.to_dict(orient="records")
    ]
