"""Outlier flags per lot: units whose calibration is unlike the rest of their lot.

Three rules, each flag naming the parameter, the unit's value, the lot median and a score:

1. **Robust z** of a unit's mean parameter across the lot's units:
   ``z = (x - median) / (1.4826 * MAD)`` (Iglewicz & Hoaglin's modified z-score). The issue
   asks for ``|z| > 3.5``. That threshold is per value; a lot of 20 units with ~24 parameters
   is ~500 values, and with 20 units the MAD itself is noisy: on Gaussian units a value
   exceeds 3.5 with probability 0.0065 (Monte Carlo, 2e5 lots), so 3.5 alone flags about three
   clean units per lot. The threshold used is therefore
   ``max(z_threshold, q)`` where ``q`` is the level that the largest |z| of one parameter over
   the lot's clean Gaussian units exceeds with probability ``family_alpha / n_parameters``
   (so a clean lot is flagged with probability about ``family_alpha``). ``q`` is computed
   once per (n_units, n_parameters) by a seeded simulation of the same statistic.
   ``family_alpha = 0`` gives the plain 3.5 rule.
   MAD = 0 (more than half the units identical): the scale falls back to
   1.2533 * mean absolute deviation (Iglewicz & Hoaglin); if that is 0 too, nothing differs.
2. **Spread**: the unit's repetition std of a parameter over the lot median of that std;
   flagged above ``spread_factor`` (default 3). Needs >= 4 repetitions: with 5 reps a clean
   unit exceeds 3x the lot median std with probability ~5e-6 per parameter (chi-square, 4 dof),
   with 2 reps it would be ~0.04.
3. **Limits** from configuration (per model/parameter ``min``/``max``), applied to every unit
   whatever the lot size.

Lots with fewer than ``min_units`` (5) units get no robust or spread flags (a median of four
units says little about what is typical); :class:`LotFlags` says so in ``note``.

Pure: inputs are a summary table (pandas), outputs dataclasses and a table.
"""
from __future__ import annotations

import math
import tomllib
from dataclasses import dataclass, field
from functools import lru_cache
from typing import Any

import numpy as np
import pandas as pd

MAD_TO_SIGMA = 1.4826  # 1 / Phi^-1(3/4): MAD of a Gaussian -> its sigma
MEANAD_TO_SIGMA = 1.2533  # sqrt(pi/2): mean absolute deviation of a Gaussian -> sigma
MIN_REPS_FOR_SPREAD = 4

KIND_ROBUST = "robust_z"
KIND_SPREAD = "spread"
KIND_LIMIT = "limit"


@dataclass(frozen=True)
class Limit:
    """Acceptance limits of one parameter (either bound may be None)."""

    model: str
    parameter: str
    min: float | None = None
    max: float | None = None


@dataclass(frozen=True)
class OutlierConfig:
    z_threshold: float = 3.5
    family_alpha: float = 0.01  # chance a clean lot gets any robust-z flag; 0 = plain threshold
    spread_factor: float = 3.0
    min_units: int = 5
    limits: tuple[Limit, ...] = ()

    def limit_of(self, model: str, parameter: str) -> Limit | None:
        for lim in self.limits:
            if lim.model == model and lim.parameter == parameter:
                return lim
        return None


class OutlierConfigError(ValueError):
    """A limits/outlier configuration that cannot be used, with the reason."""


def config_from_toml(text: str, source: str = "<config>") -> OutlierConfig:
    """Parse a TOML configuration::

        [outliers]            # all optional
        z_threshold = 3.5
        family_alpha = 0.01
        spread_factor = 3.0
        min_units = 5

        [limits.gyro.k_g11]   # [limits.<model>.<parameter>], min and/or max
        min = 0.95
        max = 1.05
    """
    try:
        doc = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise OutlierConfigError(f"{source}: not valid TOML ({exc})") from exc
    known = {"outliers", "limits"}
    unknown = set(doc) - known
    if unknown:
        raise OutlierConfigError(f"{source}: unknown section(s) {sorted(unknown)}; expected "
                                 f"[outliers] and [limits.<model>.<parameter>]")
    opts = doc.get("outliers", {})
    allowed = {"z_threshold", "family_alpha", "spread_factor", "min_units"}
    if set(opts) - allowed:
        raise OutlierConfigError(f"{source}: unknown key(s) {sorted(set(opts) - allowed)} in "
                                 f"[outliers]; allowed: {sorted(allowed)}")
    limits = []
    for model, params in doc.get("limits", {}).items():
        if not isinstance(params, dict):
            raise OutlierConfigError(f"{source}: [limits.{model}] must hold tables "
                                     f"[limits.{model}.<parameter>] with min/max")
        for name, lim in params.items():
            if not isinstance(lim, dict) or not set(lim) <= {"min", "max"} or not lim:
                raise OutlierConfigError(f"{source}: [limits.{model}.{name}] must have keys "
                                         f"min and/or max")
            lo, hi = lim.get("min"), lim.get("max")
            for v in (lo, hi):
                if v is not None and not isinstance(v, (int, float)):
                    raise OutlierConfigError(f"{source}: limits of {model}.{name} must be numbers")
            if lo is not None and hi is not None and lo > hi:
                raise OutlierConfigError(f"{source}: {model}.{name}: min {lo} > max {hi}")
            limits.append(Limit(model, name, None if lo is None else float(lo),
                                None if hi is None else float(hi)))
    try:
        cfg = OutlierConfig(
            z_threshold=float(opts.get("z_threshold", 3.5)),
            family_alpha=float(opts.get("family_alpha", 0.01)),
            spread_factor=float(opts.get("spread_factor", 3.0)),
            min_units=int(opts.get("min_units", 5)),
            limits=tuple(limits))
    except (TypeError, ValueError) as exc:
        raise OutlierConfigError(f"{source}: [outliers] values must be numbers ({exc})") from exc
    if not 0.0 <= cfg.family_alpha < 1.0:
        raise OutlierConfigError(f"{source}: family_alpha must be in [0, 1)")
    if cfg.z_threshold <= 0 or cfg.spread_factor <= 1.0 or cfg.min_units < 3:
        raise OutlierConfigError(f"{source}: need z_threshold > 0, spread_factor > 1, "
                                 f"min_units >= 3")
    return cfg


@dataclass(frozen=True)
class Flag:
    lot: str
    unit: str
    model: str
    parameter: str
    kind: str  # robust_z | spread | limit
    value: float
    lot_median: float
    score: float
    threshold: float
    reason: str


@dataclass
class LotFlags:
    lot: str
    n_units: int
    robust: bool  # robust and spread rules applied (enough units)
    z_threshold_used: float
    note: str
    flags: list[Flag] = field(default_factory=list)
    scores: pd.DataFrame | None = None  # lot, unit, model, parameter, score, lot_median

    @property
    def flagged_units(self) -> list[str]:
        return sorted({f.unit for f in self.flags})

    def to_dict(self) -> dict[str, Any]:
        return {"lot": self.lot, "n_units": self.n_units, "robust": self.robust,
                "z_threshold_used": self.z_threshold_used, "note": self.note,
                "flagged_units": self.flagged_units,
                "flags": [f.__dict__ for f in self.flags]}


# --- robust statistics ------------------------------------------------------------------------
def robust_scale(x: np.ndarray) -> float:
    """Gaussian-consistent robust scale: 1.4826 MAD, or 1.2533 mean abs deviation when the
    MAD is 0; 0.0 when every value is the same."""
    x = np.asarray(x, float)
    med = np.median(x)
    mad = np.median(np.abs(x - med))
    if mad > 0:
        return float(MAD_TO_SIGMA * mad)
    meanad = np.mean(np.abs(x - med))
    return float(MEANAD_TO_SIGMA * meanad)


def robust_z(x: np.ndarray) -> np.ndarray:
    """Modified z-scores of ``x`` (zeros when all values are equal)."""
    x = np.asarray(x, float)
    s = robust_scale(x)
    if s == 0.0:
        return np.zeros_like(x)
    return (x - np.median(x)) / s


@lru_cache(maxsize=256)
def robust_z_threshold(n_units: int, n_parameters: int, z_threshold: float = 3.5,
                       family_alpha: float = 0.01) -> float:
    """Threshold on |robust z| for a lot of ``n_units`` units and ``n_parameters`` parameters:
    ``max(z_threshold, q)`` with ``q`` exceeded by the largest |z| of one parameter over
    Gaussian units with probability ``family_alpha / n_parameters`` (seeded simulation of the
    very statistic, MAD noise included; ~1e6 draws)."""
    if family_alpha <= 0 or n_units < 3:
        return float(z_threshold)
    p = family_alpha / max(n_parameters, 1)
    rows = int(min(400_000, max(20_000, 2_000_000 // n_units)))
    rng = np.random.default_rng(20261121 + n_units)
    x = rng.normal(size=(rows, n_units))
    med = np.median(x, axis=1, keepdims=True)
    dev = np.abs(x - med)
    mad = np.median(dev, axis=1)
    scale = MAD_TO_SIGMA * mad
    zmax = dev.max(axis=1) / np.where(scale > 0, scale, np.inf)
    # tail beyond the simulated resolution: extrapolate log-linearly from the last decade
    if p * rows >= 5:
        q = float(np.quantile(zmax, 1.0 - p))
    else:
        p_hi = 50.0 / rows
        q1 = float(np.quantile(zmax, 1.0 - p_hi))
        q2 = float(np.quantile(zmax, 1.0 - p_hi / 10.0))
        q = q2 + (q2 - q1) * math.log10(p_hi / 10.0 / p)
    return float(max(z_threshold, q))


# --- flags --------------------------------------------------------------------------------------
def _fmt(v: float) -> str:
    return f"{v:.6g}"


def flag_lot(summary: pd.DataFrame, config: OutlierConfig | None = None,
             lot: str | None = None) -> LotFlags:
    """Flags of one lot from its summary rows (columns lot, unit, model, parameter, mean,
    std, n_reps, unit_of_measure optional). One row per unit and parameter."""
    cfg = config or OutlierConfig()
    need = {"unit", "model", "parameter", "mean", "std", "n_reps"}
    missing = need - set(summary.columns)
    if missing:
        raise ValueError(f"summary lacks columns {sorted(missing)}")
    if lot is None:
        lots = summary["lot"].unique() if "lot" in summary else ["?"]
        if len(lots) != 1:
            raise ValueError(f"flag_lot needs the rows of one lot, got {list(lots)}")
        lot = str(lots[0])
    df = summary.reset_index(drop=True)
    units = sorted(df["unit"].unique())
    n_units = len(units)
    n_params = int(df[["model", "parameter"]].drop_duplicates().shape[0])
    robust = n_units >= cfg.min_units
    thr = robust_z_threshold(n_units, n_params, cfg.z_threshold, cfg.family_alpha) if robust \
        else float("nan")
    if robust:
        note = (f"{n_units} units, {n_params} parameters: robust z threshold {thr:.2f} "
                f"(max of {cfg.z_threshold:g} and the family-wise level for alpha="
                f"{cfg.family_alpha:g}); spread factor {cfg.spread_factor:g}")
    else:
        note = (f"{n_units} unit(s) in lot {lot}: fewer than {cfg.min_units}, no robust z or "
                f"spread flags (only configured limits)")
    flags: list[Flag] = []
    score = np.full(len(df), np.nan)
    median = np.full(len(df), np.nan)
    for (model, name), grp in df.groupby(["model", "parameter"], sort=True):
        idx = grp.index.to_numpy()
        x = grp["mean"].to_numpy(float)
        ok = np.isfinite(x)
        if ok.any():
            med = float(np.median(x[ok]))
            median[idx] = med
            if robust and ok.sum() >= cfg.min_units:
                z = np.full(len(x), np.nan)
                z[ok] = robust_z(x[ok])
                score[idx] = z
                for i in np.flatnonzero(np.abs(np.nan_to_num(z)) > thr):
                    u = str(grp["unit"].iloc[i])
                    flags.append(Flag(lot, u, model, name, KIND_ROBUST, float(x[i]), med,
                                      float(z[i]), thr,
                                      f"{model}.{name} = {_fmt(x[i])}, lot median {_fmt(med)}, "
                                      f"robust z {z[i]:+.1f} (|z| > {thr:.2f})"))
        if robust:
            s = grp["std"].to_numpy(float)
            nr = grp["n_reps"].to_numpy(float)
            use = np.isfinite(s) & (nr >= MIN_REPS_FOR_SPREAD)
            if use.sum() >= cfg.min_units:
                med_s = float(np.median(s[use]))
                if med_s > 0:
                    ratio = np.where(use, s / med_s, np.nan)
                    for i in np.flatnonzero(np.nan_to_num(ratio) > cfg.spread_factor):
                        u = str(grp["unit"].iloc[i])
                        flags.append(Flag(
                            lot, u, model, name, KIND_SPREAD, float(s[i]), med_s,
                            float(ratio[i]), cfg.spread_factor,
                            f"{model}.{name} repetition std {_fmt(s[i])}, lot median std "
                            f"{_fmt(med_s)}, ratio {ratio[i]:.1f} (> {cfg.spread_factor:g})"))
        lim = cfg.limit_of(model, name)
        if lim is not None:
            for i in range(len(x)):
                v = x[i]
                u = str(grp["unit"].iloc[i])
                med = median[idx[i]]
                if lim.min is not None and not v >= lim.min:
                    flags.append(Flag(lot, u, model, name, KIND_LIMIT, float(v), float(med),
                                      float(v - lim.min), lim.min,
                                      f"{model}.{name} = {_fmt(v)} below limit min {_fmt(lim.min)}"
                                      f", lot median {_fmt(med)}"))
                if lim.max is not None and not v <= lim.max:
                    flags.append(Flag(lot, u, model, name, KIND_LIMIT, float(v), float(med),
                                      float(v - lim.max), lim.max,
                                      f"{model}.{name} = {_fmt(v)} above limit max {_fmt(lim.max)}"
                                      f", lot median {_fmt(med)}"))
    scores = pd.DataFrame({"lot": lot, "unit": df["unit"].to_numpy(),
                           "model": df["model"].to_numpy(), "parameter": df["parameter"].to_numpy(),
                           "score": score, "lot_median": median})
    return LotFlags(lot, n_units, robust, thr, note, flags, scores)


def apply_flags(summary: pd.DataFrame, lot_flags: list[LotFlags]) -> pd.DataFrame:
    """The summary with ``flagged``, ``flag_reason``, ``score`` and ``lot_median`` set from
    the flags (rows of lots not in ``lot_flags`` keep their values)."""
    out = summary.copy()
    for col, default in (("flagged", False), ("flag_reason", ""), ("score", np.nan),
                         ("lot_median", np.nan)):
        if col not in out:
            out[col] = default
    out["flagged"] = out["flagged"].astype(bool)
    out["flag_reason"] = out["flag_reason"].fillna("").astype(str)
    key = ["lot", "unit", "model", "parameter"]
    for lf in lot_flags:
        in_lot = (out["lot"] == lf.lot).to_numpy()
        out.loc[in_lot, "flagged"] = False
        out.loc[in_lot, "flag_reason"] = ""
        if lf.scores is not None and len(lf.scores):
            sc = out.loc[in_lot, key].merge(lf.scores, on=key, how="left")
            out.loc[in_lot, "score"] = sc["score"].to_numpy(float)
            out.loc[in_lot, "lot_median"] = sc["lot_median"].to_numpy(float)
        reasons: dict[tuple, list[str]] = {}
        for f in lf.flags:
            reasons.setdefault((f.lot, f.unit, f.model, f.parameter), []).append(
                f"[{f.kind}] {f.reason}")
        if reasons:
            ks = list(zip(*(out[c] for c in key)))
            hit = np.array([k in reasons for k in ks]) & in_lot
            out.loc[hit, "flagged"] = True
            out.loc[hit, "flag_reason"] = ["; ".join(reasons[k]) for k, h in zip(ks, hit) if h]
    return out
