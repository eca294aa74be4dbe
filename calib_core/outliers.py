"""Outlier flags per lot: units whose calibration is unlike the rest of their lot.

Three rules, each flag naming the parameter, the unit's value, the lot median and a score:

1. **Robust z** of a unit's mean parameter: ``z = (x - lot median) / (1.4826 * MAD)``
   (Iglewicz & Hoaglin's modified z-score), flagged when ``|z|`` exceeds the threshold.
   The issue asks for 3.5. That threshold is per value, and a MAD from 20 units is itself
   uncertain by ~28 %: on 20 clean Gaussian units one value exceeds 3.5 with probability
   0.0065 (Monte Carlo, 2e5 lots), so a lot of 20 units x 24 parameters would get about three
   false flags. Two things keep clean units clean:
   - the scale (MAD) of a parameter is pooled over all lots, lot-centred (``scale_pool =
     "fleet"``; each lot keeps its own median); ``"lot"`` uses each lot alone;
   - the threshold is ``max(z_threshold, q)``, ``q`` the level the largest |z| of one
     parameter over all pooled units (clean, Gaussian) exceeds with probability
     ``family_alpha / n_parameters`` (so a clean fleet gets any robust flag with probability
     about ``family_alpha``), computed once per (lot sizes, n_parameters) by a seeded
     simulation of the same statistic (3 lots of 20, 24 parameters: 6.15).
     ``family_alpha = 0`` gives the plain 3.5 rule.
   The price: a unit must be ~7-8 lot sd away to be found reliably (a 6.7 sd shift is found
   about 2 times in 3 with 3 lots of 20; 10 sd almost always); docs/flows.md has the table.
   Only the models of the applied calibration (``robust_models``: gyro, accel) get these
   flags: the traditional and static fits re-express the same quantities.
   MAD = 0 (more than half the units identical): the scale falls back to
   1.2533 * mean absolute deviation (Iglewicz & Hoaglin); if that is 0 too, nothing differs.
2. **Spread**: the unit's repetition std of a parameter over the lot median of that std;
   flagged above ``spread_factor`` (default 3). Needs >= 4 repetitions: with 5 reps a clean
   unit exceeds 3x the lot median std with probability ~5e-6 per parameter (chi-square, 4 dof),
   with 2 reps it would be ~0.04.
3. **Limits** from configuration (per model/parameter ``min``/``max`` in the stored unit,
   parsed from the engineers' TOML with units by :mod:`schemas.limits`), applied to every
   unit whatever the lot size; a separate category (``kind = "limit"``) from the two
   statistical ones.

Small lots (fewer than ``history_below`` units) are judged against the fleet's history when
the caller gives the units' acquisition times: the last ``history_units`` good units of the
lots acquired before (:func:`history_references`), with a threshold simulated for that
statistic (:func:`history_z_threshold`); ``LotFlags.reference`` says which reference was
used. Without a history, lots with fewer than ``min_units`` (5) units get no robust or spread
flags (a median of four units says little about what is typical); ``note`` says so.

Pure: inputs are a summary table (pandas), outputs dataclasses and a table.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import pandas as pd

MAD_TO_SIGMA = 1.4826  # 1 / Phi^-1(3/4): MAD of a Gaussian -> its sigma
MEANAD_TO_SIGMA = 1.2533  # sqrt(pi/2): mean absolute deviation of a Gaussian -> sigma
MIN_REPS_FOR_SPREAD = 4
MIN_UNITS_FOR_SCATTER = 3  # a lot's scatter (robust_scale of its units' means) from 3 units
# The numbers a lot's re-flag writes on each summary row of the lot, besides the flags: the
# row's robust z (``score``) and the lot's statistics of the parameter over its units (every
# unit, flagged or not): the median of the means, their robust scale, and the median of the
# units' repetition std (units with MIN_REPS_FOR_SPREAD repetitions: the spread rule's
# reference)
LOT_COLUMNS = ("score", "lot_median", "lot_scatter", "lot_median_std")
# a history reference needs at least this many good units (or history_units, if fewer)
HISTORY_MIN_UNITS = 15
# a unit of an earlier lot is "good" for the history when no robust-model parameter is further
# than this many robust sd from the fleet's median (and it fails no limit): per value a clean
# Gaussian unit is excluded with probability 6e-7
HISTORY_CLEAN_Z = 5.0

KIND_ROBUST = "robust_z"
KIND_SPREAD = "spread"
KIND_LIMIT = "limit"


@dataclass(frozen=True)
class Limit:
    """Acceptance limits of one parameter (either bound may be None), in ``unit``: the unit
    the summary stores the parameter in ("" dimensionless; None: not checked against the
    rows' ``unit_of_measure``). ``written``: the bounds as the engineer wrote them (with
    their units), for the flag reason. Parsed from TOML by :mod:`schemas.limits`."""

    model: str
    parameter: str
    min: float | None = None
    max: float | None = None
    unit: str | None = None
    written: str = ""


@dataclass(frozen=True)
class OutlierConfig:
    z_threshold: float = 3.5
    family_alpha: float = 0.01  # chance a clean lot gets any robust-z flag; 0 = plain threshold
    spread_factor: float = 3.0
    min_units: int = 5
    limits: tuple[Limit, ...] = ()
    # models whose parameters get robust-z and spread flags: the applied calibration. The
    # traditional and static fits re-express the same quantities and would only multiply
    # the number of tests (and so the threshold) without finding other units.
    robust_models: tuple[str, ...] = ("gyro", "accel")
    scale_pool: str = "fleet"  # fleet: lot-centred MAD over all lots; lot: each lot alone
    # lots with fewer units than history_below are judged against the last history_units
    # good units of earlier lots (by acquisition time) when there are at least
    # min(history_units, HISTORY_MIN_UNITS) of them; 0 turns the history reference off
    history_units: int = 60
    history_below: int = 20
    # "lot": a small lot's units against its own median with the history's (lot-centred)
    # scale, robust to lot-to-lot offsets; "history": against the history's median and scale
    history_location: str = "lot"

    def __post_init__(self) -> None:
        for name in ("z_threshold", "family_alpha", "spread_factor"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not np.isfinite(v):
                raise OutlierConfigError(f"{name} must be a finite number, got {v!r}")
        if self.scale_pool not in ("fleet", "lot"):
            raise OutlierConfigError("scale_pool must be 'fleet' or 'lot'")
        if not 0.0 <= self.family_alpha < 1.0:
            raise OutlierConfigError("family_alpha must be in [0, 1)")
        if self.z_threshold <= 0 or self.spread_factor <= 1.0 or self.min_units < 3:
            raise OutlierConfigError("need z_threshold > 0, spread_factor > 1, min_units >= 3")
        if self.history_location not in ("lot", "history"):
            raise OutlierConfigError("history_location must be 'lot' or 'history'")
        if self.history_units < 0 or self.history_below < 0:
            raise OutlierConfigError("history_units and history_below must be >= 0")

    def limit_of(self, model: str, parameter: str) -> Limit | None:
        for lim in self.limits:
            if lim.model == model and lim.parameter == parameter:
                return lim
        return None

    def uses_history(self) -> bool:
        return self.history_units > 0 and self.history_below > 0


class OutlierConfigError(ValueError):
    """A limits/outlier configuration that cannot be used, with the reason."""


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
    scores: pd.DataFrame | None = None  # lot, unit, model, parameter, *LOT_COLUMNS
    # what the robust z was computed against: "lot" (its own median, the pooled or lot
    # scale), "fleet history" (median and scale of the last good units of earlier lots) or
    # "none" (too few units and no history)
    reference: str = "lot"
    reference_detail: str = ""

    @property
    def flagged_units(self) -> list[str]:
        return sorted({f.unit for f in self.flags})

    def to_dict(self) -> dict[str, Any]:
        return {
            "lot": self.lot,
            "n_units": self.n_units,
            "robust": self.robust,
            "z_threshold_used": self.z_threshold_used,
            "note": self.note,
            "reference": self.reference,
            "reference_detail": self.reference_detail,
            "flagged_units": self.flagged_units,
            "flags": [f.__dict__ for f in self.flags],
        }


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


def lot_statistics(means: np.ndarray, stds: np.ndarray, n_reps: np.ndarray) -> tuple[float, float, float]:
    """A parameter's statistics over a lot's units (every unit, flagged or not), from their
    summary rows: the median of the finite means (``lot_median``), their robust scale from
    MIN_UNITS_FOR_SCATTER units (``lot_scatter``) and the median repetition std of the units
    with MIN_REPS_FOR_SPREAD repetitions (``lot_median_std``: the spread rule's reference);
    NaN where there are too few."""
    x = np.asarray(means, float)
    x = x[np.isfinite(x)]
    s, n = np.asarray(stds, float), np.asarray(n_reps, float)
    spread = np.isfinite(s) & (n >= MIN_REPS_FOR_SPREAD)
    return (
        float(np.median(x)) if len(x) else float("nan"),
        robust_scale(x) if len(x) >= MIN_UNITS_FOR_SCATTER else float("nan"),
        float(np.median(s[spread])) if spread.any() else float("nan"),
    )


def robust_z(x: np.ndarray) -> np.ndarray:
    """Modified z-scores of ``x`` (zeros when all values are equal)."""
    x = np.asarray(x, float)
    s = robust_scale(x)
    if s == 0.0:
        return np.zeros_like(x)
    return (x - np.median(x)) / s


# Bump THRESHOLD_SIMULATION_VERSION when the simulation of a threshold changes, so that the
# values a results store kept from earlier runs are not reused.
THRESHOLD_SIMULATION_VERSION = 1


def _threshold_key(
    sizes: tuple[int, ...], n_parameters: int, z_threshold: float, family_alpha: float
) -> tuple:
    return (tuple(sizes), int(n_parameters), float(z_threshold), float(family_alpha))


class ThresholdTable:
    """The robust-z thresholds of one run, each simulated once per lot layout.

    The simulation is deterministic (seeded) but costs 1-2 s of CPU per layout, and a fleet
    has few layouts. The caller owns the table: it makes one per run (from the document an
    earlier run kept, :meth:`document`), passes it to every :func:`flag_lots` of that run and
    keeps the document again. Nothing in calib_core outlives the call that was given the table.
    """

    def __init__(self, document: dict | None = None) -> None:
        self._q: dict[tuple, float] = {}
        self.take(document)

    def __len__(self) -> int:
        return len(self._q)

    def take(self, document: dict | None) -> int:
        """Take the thresholds of an earlier run's :meth:`document`; a document of another
        simulation version, or malformed entries, are ignored. Returns how many were taken."""
        if not isinstance(document, dict) or document.get("version") != THRESHOLD_SIMULATION_VERSION:
            return 0
        n = 0
        for e in document.get("thresholds") or []:
            try:
                key = _threshold_key(
                    tuple(int(x) for x in e["group_sizes"]),
                    e["n_parameters"],
                    e["z_threshold"],
                    e["family_alpha"],
                )
                q = float(e["q"])
            except (KeyError, TypeError, ValueError):
                continue
            if math.isfinite(q):
                self._q.setdefault(key, q)
                n += 1
        return n

    def document(self) -> dict:
        """The thresholds known to this table, as a JSON-ready document."""
        return {
            "version": THRESHOLD_SIMULATION_VERSION,
            "thresholds": [
                {
                    "group_sizes": list(k[0]),
                    "n_parameters": k[1],
                    "z_threshold": k[2],
                    "family_alpha": k[3],
                    "q": v,
                }
                for k, v in sorted(self._q.items())
            ],
        }

    def robust_z(
        self,
        group_sizes: int | tuple[int, ...],
        n_parameters: int,
        z_threshold: float = 3.5,
        family_alpha: float = 0.01,
    ) -> float:
        """Threshold on |robust z| for one parameter: ``max(z_threshold, q)`` where ``q`` is
        exceeded by the largest |z| over all units with probability ``family_alpha /
        n_parameters`` when every unit is clean and Gaussian.

        ``group_sizes``: units per lot whose lot-centred values share one MAD (a single int: one
        lot with its own MAD). ``q`` comes from a seeded simulation of exactly that statistic:
        centring on each lot's own median shrinks the deviations and the MAD, which raises the
        tail (3 lots of 20 need 5.99 where one group of 60 needs 5.72, at 0.01/24)."""
        sizes = (
            (int(group_sizes),)
            if isinstance(group_sizes, (int, np.integer))
            else tuple(sorted(int(n) for n in group_sizes))
        )
        if family_alpha <= 0 or sum(sizes) < 3:
            return float(z_threshold)
        key = _threshold_key(sizes, n_parameters, z_threshold, family_alpha)
        if key not in self._q:
            self._q[key] = _robust_q(sizes, n_parameters, family_alpha)
        return float(max(z_threshold, self._q[key]))

    def history_z(
        self,
        history_groups: tuple[int, ...],
        n_lot: int,
        n_parameters: int,
        z_threshold: float = 3.5,
        family_alpha: float = 0.01,
        location: str = "lot",
    ) -> float:
        """Threshold on the robust z of the ``n_lot`` units of a small lot judged against a
        history of earlier units (``history_groups``: how many of them per earlier lot):
        ``max(z_threshold, q)``, ``q`` exceeded by the largest of the ``n_lot`` |z| with
        probability ``family_alpha / n_parameters`` when every unit is clean and Gaussian, from
        a seeded simulation of that very statistic:

        - ``location="lot"``: ``z = (x - lot median) / s``, ``s`` the robust scale of the
          history's values each centred on its own lot's median (the lot's median from its few
          units is uncertain, the scale from the history much less);
        - ``location="history"``: ``z = (x - history median) / s``, ``s`` the history's robust
          scale (history median and scale both uncertain; lots are assumed to share one mean).

        Kept in a :class:`ThresholdTable` under the group sizes ``(0, n_lot, *history_groups)``
        ("lot") or ``(0, 0, n_lot, *history_groups)`` ("history"): a real layout never has a
        lot of 0 units."""
        groups = tuple(sorted(int(g) for g in history_groups))
        n_lot = int(n_lot)
        if family_alpha <= 0 or sum(groups) < 3 or n_lot < 1:
            return float(z_threshold)
        tag = (0, n_lot) if location == "lot" else (0, 0, n_lot)
        key = _threshold_key(tag + groups, n_parameters, z_threshold, family_alpha)
        if key not in self._q:
            self._q[key] = _history_q(groups, n_lot, n_parameters, family_alpha, location, tag)
        return float(max(z_threshold, self._q[key]))


def robust_z_threshold(
    group_sizes: int | tuple[int, ...],
    n_parameters: int,
    z_threshold: float = 3.5,
    family_alpha: float = 0.01,
) -> float:
    """:meth:`ThresholdTable.robust_z` simulated afresh (nothing kept)."""
    return ThresholdTable().robust_z(group_sizes, n_parameters, z_threshold, family_alpha)


def history_z_threshold(
    history_groups: tuple[int, ...],
    n_lot: int,
    n_parameters: int,
    z_threshold: float = 3.5,
    family_alpha: float = 0.01,
    location: str = "lot",
) -> float:
    """:meth:`ThresholdTable.history_z` simulated afresh (nothing kept)."""
    return ThresholdTable().history_z(
        history_groups, n_lot, n_parameters, z_threshold, family_alpha, location
    )


def _robust_q(sizes: tuple[int, ...], n_parameters: int, family_alpha: float) -> float:
    """The simulated ``q`` of :meth:`ThresholdTable.robust_z` (sizes sorted)."""
    total = sum(sizes)
    p = family_alpha / max(n_parameters, 1)
    # ~2e7 normal draws at most, in chunks of ~2e6 (memory stays ~50 MB)
    rows = int(min(200.0 / p, max(2_000, 20_000_000 // total)))
    chunk = max(1, 2_000_000 // total)
    rng = np.random.default_rng(20261121 + 7919 * total + len(sizes))
    zmax_parts = [_simulated_zmax(rng, min(chunk, rows - start), sizes) for start in range(0, rows, chunk)]
    zmax = np.concatenate(zmax_parts)
    if p * rows >= 20:
        q = float(np.quantile(zmax, 1.0 - p))
    else:  # beyond the simulated resolution: extrapolate log-linearly from the last decade
        p_hi = 200.0 / rows
        q1 = float(np.quantile(zmax, 1.0 - p_hi))
        q2 = float(np.quantile(zmax, 1.0 - p_hi / 10.0))
        q = q2 + (q2 - q1) * math.log10(p_hi / 10.0 / p)
    return float(q)


def _history_q(
    groups: tuple[int, ...], n_lot: int, n_parameters: int, family_alpha: float, location: str, tag: tuple
) -> float:
    """The simulated ``q`` of :meth:`ThresholdTable.history_z` (groups sorted)."""
    n_history = sum(groups)
    p = family_alpha / max(n_parameters, 1)
    total = n_history + n_lot
    rows = int(min(200.0 / p, max(2_000, 20_000_000 // total)))
    chunk = max(1, 2_000_000 // total)
    rng = np.random.default_rng([20261124, n_lot, len(tag), *groups])
    parts = []
    for start in range(0, rows, chunk):
        m = min(chunk, rows - start)
        lot = rng.standard_normal((m, n_lot))
        if location == "lot":
            dev = np.empty((m, n_history))
            col = 0
            for g in groups:  # each earlier lot centred on its own median
                block = rng.standard_normal((m, g))
                block.sort(axis=1)
                dev[:, col : col + g] = np.abs(block - _sorted_median(block)[:, None])
                col += g
            lot_sorted = np.sort(lot, axis=1)
            centre = _sorted_median(lot_sorted)
        else:
            hist = rng.standard_normal((m, n_history))
            hist.sort(axis=1)
            centre = _sorted_median(hist)
            dev = np.abs(hist - centre[:, None])
        dev.sort(axis=1)
        scale = MAD_TO_SIGMA * _sorted_median(dev)
        parts.append(np.abs(lot - centre[:, None]).max(axis=1) / np.where(scale > 0, scale, np.inf))
    zmax = np.concatenate(parts)
    if p * rows >= 20:
        q = float(np.quantile(zmax, 1.0 - p))
    else:
        p_hi = 200.0 / rows
        q1 = float(np.quantile(zmax, 1.0 - p_hi))
        q2 = float(np.quantile(zmax, 1.0 - p_hi / 10.0))
        q = q2 + (q2 - q1) * math.log10(p_hi / 10.0 / p)
    return float(q)


def _simulated_zmax(rng: np.random.Generator, m: int, sizes: tuple[int, ...]) -> np.ndarray:
    """``m`` draws of the largest lot-centred |z| of clean Gaussian lots of ``sizes`` units
    (sorted), the draws taken from ``rng`` in the order lot by lot, (m, n) each.

    Each lot's (m, n) block is drawn into its columns of the (m, total) array of deviations
    (the same numbers in the same order as one (k, m, n) call for k lots of one size), so the
    memory is that array plus one lot's block, whatever the number of lots (a (k, m, n) draw
    transposed to unit rows was a second copy of the whole chunk). Medians and maxima do not
    depend on the order of a row, so each row is sorted in place and read at its middle and
    end: numpy's vectorised sort of short rows costs ~1/5 of ``np.median``'s selection, and
    the middle of a sorted row is the same number (for an even count the mean of the two
    middle values, as ``np.median`` takes it)."""
    total = sum(sizes)
    dev = np.empty((m, total))
    col = 0
    for n in sizes:
        # one lot is drawn in place (``out`` takes only a whole contiguous array)
        block = rng.standard_normal(out=dev) if n == total else rng.standard_normal((m, n))
        block.sort(axis=-1)
        np.subtract(block, _sorted_median(block)[..., None], out=block)
        np.abs(block, out=block)
        if block is not dev:
            dev[:, col : col + n] = block
        col += n
    dev.sort(axis=1)
    scale = MAD_TO_SIGMA * _sorted_median(dev)
    return dev[:, -1] / np.where(scale > 0, scale, np.inf)


def _sorted_median(s: np.ndarray) -> np.ndarray:
    """Median along the last axis of rows already sorted: ``np.median``'s value."""
    n = s.shape[-1]
    h = n // 2
    return s[..., h] if n % 2 else (s[..., h - 1] + s[..., h]) / 2


# --- flags --------------------------------------------------------------------------------------
def _fmt(v: float) -> str:
    return f"{v:.6g}"


def _key_groups(*cols: np.ndarray) -> list[tuple[tuple, np.ndarray]]:
    """(key, row positions in their original order) per distinct key tuple of ``cols``, keys
    in sorted order: what ``DataFrame.groupby(cols, sort=True)`` iterates, without a pandas
    frame per group (a lot of 50 units has ~70 parameters: the slicing cost more than the
    statistics)."""
    n = len(cols[0])
    if n == 0:
        return []
    code = np.zeros(n, np.int64)
    for c in cols:
        # hashing, then a sort of the distinct values only (not of every row's string)
        inv, uniques = pd.factorize(c, sort=True)
        code = code * (len(uniques) + 1) + inv  # -1: a missing key
    missing = np.zeros(n, bool)
    for c in cols:
        missing |= pd.isna(c)
    if missing.any():  # groupby leaves rows with a missing key out
        code = np.where(missing, -1, code)
    order = np.argsort(code, kind="stable")  # rows of a group keep their order
    sorted_code = code[order]
    starts = np.flatnonzero(np.r_[True, sorted_code[1:] != sorted_code[:-1]])
    ends = np.r_[starts[1:], n]
    out = []
    for a, b in zip(starts.tolist(), ends.tolist()):
        if sorted_code[a] < 0:
            continue
        rows = order[a:b]
        first = rows[0]
        out.append((tuple(c[first] for c in cols), rows))
    return out


def _lot_centred_scales(
    df: pd.DataFrame, min_units: int
) -> dict[tuple[str, str], tuple[float, tuple[int, ...]]]:
    """Per (model, parameter): robust scale of the lot-centred unit means, pooled over every
    lot with at least ``min_units`` units, and the number of units pooled."""
    out: dict[tuple[str, str], tuple[float, tuple[int, ...]]] = {}
    model_col = df["model"].to_numpy(object)
    name_col = df["parameter"].to_numpy(object)
    lot_col = df["lot"].to_numpy(object)
    mean_col = df["mean"].to_numpy(float)
    for (model, name), rows in _key_groups(model_col, name_col):
        parts, sizes = [], []
        for _, lot_rows in _key_groups(lot_col[rows]):  # lots in sorted order
            x = mean_col[rows[lot_rows]]
            x = x[np.isfinite(x)]
            if len(x) >= min_units:
                parts.append(x - np.median(x))
                sizes.append(len(x))
        if parts:
            # MAD about 0 (each lot is centred on its own median), as robust_z_threshold
            # simulates it; mean absolute deviation when more than half are exactly 0
            c = np.abs(np.concatenate(parts))
            mad = float(np.median(c))
            scale = MAD_TO_SIGMA * mad if mad > 0 else MEANAD_TO_SIGMA * float(np.mean(c))
            out[(model, name)] = (scale, tuple(sorted(sizes)))
    return out


@dataclass(frozen=True)
class HistoryReference:
    """What a small lot is judged against: per (model, parameter) the median and robust scale
    of the last good units of earlier lots."""

    stats: dict[tuple[str, str], tuple[float, float, int]]  # median, scale, n values
    centred: dict[tuple[str, str], tuple[float, tuple[int, ...]]]  # lot-centred scale, groups
    n_units: int
    lots: tuple[str, ...]
    detail: str


def _limit_failures(df: pd.DataFrame, cfg: OutlierConfig) -> set[tuple[str, str]]:
    """(lot, unit) of the units failing any configured limit."""
    out: set[tuple[str, str]] = set()
    for lim in cfg.limits:
        rows = df[(df["model"] == lim.model) & (df["parameter"] == lim.parameter)]
        v = rows["mean"].to_numpy(float)
        bad = np.zeros(len(v), bool)
        if lim.min is not None:
            bad |= ~(v >= lim.min)
        if lim.max is not None:
            bad |= ~(v <= lim.max)
        out.update(zip(rows["lot"].to_numpy(object)[bad], rows["unit"].to_numpy(object)[bad]))
    return out


def history_references(
    summary: pd.DataFrame, config: OutlierConfig, unit_times: dict[tuple[str, str], float], lots: list[str]
) -> dict[str, HistoryReference]:
    """The history reference of each lot of ``lots`` with fewer than ``history_below`` units
    that has one: the last ``history_units`` good units (by acquisition time,
    ``unit_times[(lot, unit)]`` in seconds) of the lots acquired before it (a lot's time is
    its first unit's). A good unit fails no limit and has every robust-model parameter within
    ``HISTORY_CLEAN_Z`` robust sd of the fleet's median (the fleet: every unit of
    ``summary``). Lots without enough good earlier units (fewer than
    ``min(history_units, HISTORY_MIN_UNITS)``) or without a time get none."""
    cfg = config
    if not cfg.uses_history() or not unit_times or not len(summary):
        return {}
    df = summary[["lot", "unit", "model", "parameter", "mean"]].copy()
    df["lot"] = df["lot"].astype(str)
    df["unit"] = df["unit"].astype(str)
    n_units = df.groupby("lot")["unit"].nunique()
    small = [lot for lot in lots if lot in n_units.index and n_units[lot] < cfg.history_below]
    if not small:
        return {}
    robust = df[df["model"].isin(cfg.robust_models)] if cfg.robust_models else df
    wide = robust.pivot_table(
        index=["lot", "unit"], columns=["model", "parameter"], values="mean", aggfunc="first"
    )
    if not len(wide):
        return {}
    X = wide.to_numpy(float)
    med = np.nanmedian(X, axis=0)
    scale = np.array([robust_scale(c[np.isfinite(c)]) if np.isfinite(c).any() else 0.0 for c in X.T])
    with np.errstate(invalid="ignore", divide="ignore"):
        z = np.abs(X - med) / np.where(scale > 0, scale, np.inf)
    keys = list(wide.index)
    failing = _limit_failures(df, cfg)
    good = np.array(
        [
            not (np.nan_to_num(z[i]) > HISTORY_CLEAN_Z).any() and keys[i] not in failing
            for i in range(len(keys))
        ],
        bool,
    )
    t_unit = np.array([unit_times.get(k, np.nan) for k in keys], float)
    lot_time: dict[str, float] = {}
    for (lot, _), t in zip(keys, t_unit):
        if np.isfinite(t):
            lot_time[lot] = min(lot_time.get(lot, np.inf), t)
    lot_of = np.array([k[0] for k in keys], object)
    need = min(cfg.history_units, HISTORY_MIN_UNITS)
    out: dict[str, HistoryReference] = {}
    for lot in small:
        t0 = lot_time.get(lot)
        if t0 is None:
            continue
        earlier = np.array([lot_time.get(x, np.inf) < t0 for x in lot_of], bool)
        cand = np.flatnonzero(good & earlier & np.isfinite(t_unit))
        if len(cand) < need:
            continue
        # newest first; ties by (lot, unit) for a deterministic choice
        order = sorted(cand.tolist(), key=lambda i: (-t_unit[i], keys[i]))
        chosen = np.array(order[: cfg.history_units])
        stats, centred = {}, {}
        chosen_lots = lot_of[chosen]
        for j, col in enumerate(wide.columns):
            v = X[chosen, j]
            fin = np.isfinite(v)
            if fin.sum() < need:
                continue
            key = (str(col[0]), str(col[1]))
            stats[key] = (float(np.median(v[fin])), robust_scale(v[fin]), int(fin.sum()))
            # each chosen unit centred on the median of all its lot's units; MAD about 0
            dev, groups = [], []
            for lot_h in sorted(set(chosen_lots.tolist())):
                all_of_lot = X[lot_of == lot_h, j]
                all_of_lot = all_of_lot[np.isfinite(all_of_lot)]
                mine = v[(chosen_lots == lot_h) & fin]
                if len(mine) and len(all_of_lot):
                    dev.append(mine - np.median(all_of_lot))
                    groups.append(len(mine))
            c = np.abs(np.concatenate(dev))
            mad = float(np.median(c))
            scale = MAD_TO_SIGMA * mad if mad > 0 else MEANAD_TO_SIGMA * float(np.mean(c))
            centred[key] = (scale, tuple(sorted(groups)))
        used_lots = tuple(sorted({str(lot_of[i]) for i in chosen}))
        how = (
            "the lot's own median and the spread of"
            if cfg.history_location == "lot"
            else "the median and spread of"
        )
        detail = (
            f"{how} the fleet history: {len(chosen)} good units, the last of lots "
            f"acquired before this one ({', '.join(used_lots)})"
        )
        out[lot] = HistoryReference(stats, centred, len(chosen), used_lots, detail)
    return out


def flag_lots(
    summary: pd.DataFrame,
    config: OutlierConfig | None = None,
    lots: list[str] | None = None,
    unit_times: dict[tuple[str, str], float] | None = None,
    thresholds: ThresholdTable | None = None,
) -> list[LotFlags]:
    """Flags of each lot (all lots in ``summary`` unless ``lots`` is given). ``summary`` has
    one row per lot, unit, model and parameter with columns lot, unit, model, parameter,
    mean, std, n_reps.

    With ``scale_pool="fleet"`` (default) the robust scale of a parameter is the MAD of the
    lot-centred unit means over every lot of ``summary`` with enough units: a MAD from 20
    units is itself uncertain by ~28 % and that, not the data, is what makes clean units cross
    3.5. Location is the lot's own median. ``scale_pool="lot"`` uses each lot alone.

    ``unit_times`` ((lot, unit) -> acquisition time, s): lots with fewer than
    ``history_below`` units are judged against the fleet's history instead
    (:func:`history_references`) when they have one; without it, as above.

    ``thresholds``: the run's :class:`ThresholdTable` (None: one for this call only)."""
    cfg = config or OutlierConfig()
    thresholds = ThresholdTable() if thresholds is None else thresholds
    need = {"lot", "unit", "model", "parameter", "mean", "std", "n_reps"}
    missing = need - set(summary.columns)
    if missing:
        raise ValueError(f"summary lacks columns {sorted(missing)}")
    df = summary.reset_index(drop=True).copy()
    df["lot"] = df["lot"].astype(str)
    df["unit"] = df["unit"].astype(str)
    robust_rows = (
        df["model"].isin(cfg.robust_models) if cfg.robust_models else pd.Series(True, index=df.index)
    )
    pooled = _lot_centred_scales(df[robust_rows], cfg.min_units) if cfg.scale_pool == "fleet" else {}
    robust = robust_rows.to_numpy(bool)
    todo = sorted(df["lot"].unique()) if lots is None else [str(x) for x in lots]
    # the columns as numpy arrays once (not a frame per lot and per parameter)
    cols = {c: df[c].to_numpy(object) for c in ("lot", "unit", "model", "parameter")}
    cols.update({c: df[c].to_numpy(float) for c in ("mean", "std", "n_reps")})
    if "unit_of_measure" in df:
        cols["unit_of_measure"] = df["unit_of_measure"].to_numpy(object)
    history = history_references(df, cfg, unit_times or {}, todo)
    out = []
    for lot in todo:
        in_lot = cols["lot"] == lot
        n_params = len(
            set(zip(cols["model"][in_lot & robust].tolist(), cols["parameter"][in_lot & robust].tolist()))
        )
        rows = np.flatnonzero(in_lot)
        out.append(
            _flag_one_lot(
                {c: v[rows] for c, v in cols.items()},
                n_params,
                lot,
                cfg,
                pooled,
                thresholds,
                history.get(lot),
            )
        )
    return out


def flag_lot(
    summary: pd.DataFrame,
    config: OutlierConfig | None = None,
    lot: str | None = None,
    thresholds: ThresholdTable | None = None,
) -> LotFlags:
    """Flags of one lot using that lot's rows only (its own scale)."""
    cfg = config or OutlierConfig()
    if lot is None:
        lots = summary["lot"].unique()
        if len(lots) != 1:
            raise ValueError(f"flag_lot needs the rows of one lot, got {list(lots)}")
        lot = str(lots[0])
    rows = summary[summary["lot"].astype(str) == str(lot)]
    local = OutlierConfig(**{**cfg.__dict__, "scale_pool": "lot"})
    return flag_lots(rows, local, [str(lot)], thresholds=thresholds)[0]


def _same_unit(stored: Any, limit_unit: str) -> bool:
    """Whether a row's ``unit_of_measure`` is the unit a limit is in ("A per A" and "A/A"
    are dimensionless, "")."""
    u = "" if stored is None or (isinstance(stored, float) and math.isnan(stored)) else str(stored).strip()
    for sep in (" per ", "/"):
        parts = u.split(sep)
        if len(parts) == 2 and parts[0].strip() == parts[1].strip():
            u = ""
    return u in ("", "1") if limit_unit == "" else u == limit_unit


def _flag_one_lot(
    cols: dict[str, np.ndarray],
    n_params: int,
    lot: str,
    cfg: OutlierConfig,
    pooled: dict[tuple[str, str], tuple[float, tuple[int, ...]]],
    table: ThresholdTable,
    history: HistoryReference | None = None,
) -> LotFlags:
    """Flags of one lot: ``cols`` its rows' columns (unit, model, parameter, mean, std,
    n_reps, optionally unit_of_measure), ``n_params`` its number of distinct (model,
    parameter) in the robust models; ``history``: judge the robust z against it."""
    unit_col = cols["unit"]
    units = sorted(set(unit_col.tolist()))
    n_units = len(units)
    robust = n_units >= cfg.min_units
    flags: list[Flag] = []
    n_rows = len(unit_col)
    score = np.full(n_rows, np.nan)
    median = np.full(n_rows, np.nan)
    scatter = np.full(n_rows, np.nan)
    median_std = np.full(n_rows, np.nan)
    thresholds: list[float] = []
    limit_notes: list[str] = []
    mean_col, std_col, nreps_col = cols["mean"], cols["std"], cols["n_reps"]
    uom_col = cols.get("unit_of_measure")
    for (model, name), idx in _key_groups(cols["model"], cols["parameter"]):
        x = mean_col[idx]
        grp_units = unit_col[idx]
        ok = np.isfinite(x)
        if not ok.any():
            continue
        med, scatter[idx], median_std[idx] = lot_statistics(x, std_col[idx], nreps_col[idx])
        median[idx] = med
        s_all = std_col[idx]
        rep_spread = np.isfinite(s_all) & (nreps_col[idx] >= MIN_REPS_FOR_SPREAD)
        in_robust = (not cfg.robust_models) or model in cfg.robust_models
        ref = history.stats.get((model, name)) if history is not None else None
        if in_robust and ref is not None:
            if cfg.history_location == "history":
                ref_med, scale, n_hist = ref
                groups: tuple[int, ...] = (n_hist,)
                where = f"fleet history median {_fmt(ref_med)} ({n_hist} units)"
            else:
                ref_med = med
                scale, groups = history.centred[(model, name)]
                where = f"lot median {_fmt(med)}, scale of the fleet history ({sum(groups)} units)"
            thr = table.history_z(
                groups, int(ok.sum()), n_params, cfg.z_threshold, cfg.family_alpha, cfg.history_location
            )
            thresholds.append(thr)
            z = np.where(ok, (x - ref_med) / scale, np.nan) if scale > 0 else np.zeros(len(x))
            score[idx] = z
            for i in np.flatnonzero(np.abs(np.nan_to_num(z)) > thr):
                flags.append(
                    Flag(
                        lot,
                        str(grp_units[i]),
                        model,
                        name,
                        KIND_ROBUST,
                        float(x[i]),
                        ref_med,
                        float(z[i]),
                        thr,
                        f"{model}.{name} = {_fmt(x[i])}, {where}, robust z {z[i]:+.1f} (|z| > {thr:.2f})",
                    )
                )
        elif robust and in_robust and ok.sum() >= cfg.min_units:
            if (model, name) in pooled:
                scale, n_pool = pooled[(model, name)]
            else:
                scale, n_pool = robust_scale(x[ok]), (int(ok.sum()),)
            thr = table.robust_z(n_pool, n_params, cfg.z_threshold, cfg.family_alpha)
            thresholds.append(thr)
            z = np.where(ok, (x - med) / scale, np.nan) if scale > 0 else np.zeros(len(x))
            score[idx] = z
            for i in np.flatnonzero(np.abs(np.nan_to_num(z)) > thr):
                u = str(grp_units[i])
                flags.append(
                    Flag(
                        lot,
                        u,
                        model,
                        name,
                        KIND_ROBUST,
                        float(x[i]),
                        med,
                        float(z[i]),
                        thr,
                        f"{model}.{name} = {_fmt(x[i])}, lot median {_fmt(med)}, "
                        f"robust z {z[i]:+.1f} (|z| > {thr:.2f})",
                    )
                )
        if robust and in_robust and ok.sum() >= cfg.min_units:
            s, use = s_all, rep_spread
            if use.sum() >= cfg.min_units:
                med_s = float(median_std[idx[0]])
                if med_s > 0:
                    ratio = np.where(use, s / med_s, np.nan)
                    for i in np.flatnonzero(np.nan_to_num(ratio) > cfg.spread_factor):
                        u = str(grp_units[i])
                        flags.append(
                            Flag(
                                lot,
                                u,
                                model,
                                name,
                                KIND_SPREAD,
                                float(s[i]),
                                med_s,
                                float(ratio[i]),
                                cfg.spread_factor,
                                f"{model}.{name} repetition std {_fmt(s[i])}, lot median std "
                                f"{_fmt(med_s)}, ratio {ratio[i]:.1f} (> {cfg.spread_factor:g})",
                            )
                        )
        lim = cfg.limit_of(model, name)
        if lim is not None:
            if lim.unit is not None and uom_col is not None:
                stored = uom_col[idx]
                wrong = {str(u) for u in stored if not _same_unit(u, lim.unit)}
                if wrong:
                    limit_notes.append(
                        f"limit of {model}.{name} not applied: it is in "
                        f"{lim.unit or 'dimensionless'!r}, the values in "
                        f"{', '.join(sorted(wrong))}"
                    )
                    continue
            u_txt = f" {lim.unit}" if lim.unit else ""
            for i in range(len(x)):
                v = x[i]
                u = str(grp_units[i])
                written = f" (limit {lim.written})" if lim.written else ""
                for bound, side, outside in (
                    (lim.min, "below limit min", lim.min is not None and not v >= lim.min),
                    (lim.max, "above limit max", lim.max is not None and not v <= lim.max),
                ):
                    if outside:
                        flags.append(
                            Flag(
                                lot,
                                u,
                                model,
                                name,
                                KIND_LIMIT,
                                float(v),
                                med,
                                float(v - bound),
                                bound,
                                f"{model}.{name} = {_fmt(v)}{u_txt} {side} {_fmt(bound)}{u_txt}{written}",
                            )
                        )
    thr_used = float(np.median(thresholds)) if thresholds else float("nan")
    if history is not None:
        reference, detail = "fleet history", history.detail
        note = (
            f"{n_units} units in lot {lot} (fewer than {cfg.history_below}): judged "
            f"with {detail}; |robust z| threshold {thr_used:.2f} (max of "
            f"{cfg.z_threshold:g} and the family-wise level for alpha="
            f"{cfg.family_alpha:g})"
        )
        if robust:
            note += f"; spread factor {cfg.spread_factor:g} within the lot"
    elif robust:
        reference, detail = "lot", f"lot {lot}'s own median, scale {cfg.scale_pool}"
        note = (
            f"{n_units} units, {n_params} parameters in robust models "
            f"{', '.join(cfg.robust_models) or 'all'}: |robust z| threshold "
            f"{thr_used:.2f} (max of {cfg.z_threshold:g} and the family-wise level for "
            f"alpha={cfg.family_alpha:g}; scale {cfg.scale_pool}); spread factor "
            f"{cfg.spread_factor:g}"
        )
        if cfg.uses_history() and n_units < cfg.history_below:
            note += "; no fleet history of earlier lots to judge this small lot against"
    else:
        reference, detail = "none", "too few units and no fleet history of earlier lots"
        note = (
            f"{n_units} unit(s) in lot {lot}: fewer than {cfg.min_units} and no fleet "
            f"history of earlier lots, no robust z or spread flags (only configured limits)"
        )
    if limit_notes:
        note += "; " + "; ".join(limit_notes)
    scores = pd.DataFrame(
        {
            "lot": lot,
            "unit": unit_col,
            "model": cols["model"],
            "parameter": cols["parameter"],
            "score": score,
            "lot_median": median,
            "lot_scatter": scatter,
            "lot_median_std": median_std,
        }
    )
    return LotFlags(
        lot, n_units, robust or history is not None, thr_used, note, flags, scores, reference, detail
    )


def apply_flags(summary: pd.DataFrame, lot_flags: list[LotFlags]) -> pd.DataFrame:
    """The summary with ``flagged``, ``flag_reason`` and the columns of :data:`LOT_COLUMNS`
    set from the flags (rows of lots not in ``lot_flags`` keep their values)."""
    out = summary.copy()
    for col, default in (("flagged", False), ("flag_reason", ""), *((c, np.nan) for c in LOT_COLUMNS)):
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
            for col in LOT_COLUMNS:
                out.loc[in_lot, col] = sc[col].to_numpy(float)
        reasons: dict[tuple, list[str]] = {}
        for f in lf.flags:
            reasons.setdefault((f.lot, f.unit, f.model, f.parameter), []).append(f"[{f.kind}] {f.reason}")
        if reasons:
            ks = list(zip(*(out[c] for c in key)))
            hit = np.array([k in reasons for k in ks]) & in_lot
            out.loc[hit, "flagged"] = True
            out.loc[hit, "flag_reason"] = ["; ".join(reasons[k]) for k, h in zip(ks, hit) if h]
    return out


# --- what ties one lot's flags to the other lots --------------------------------------------------
def pooling_rows(summary: pd.DataFrame, config: OutlierConfig | None = None) -> pd.DataFrame:
    """The rows and columns of ``summary`` that the pooled scales of :func:`flag_lots` are
    computed from (lot, unit, model, parameter, mean of the robust models), in their order.
    With ``scale_pool="lot"`` no row is pooled."""
    cfg = config or OutlierConfig()
    cols = ["lot", "unit", "model", "parameter", "mean"]
    if cfg.scale_pool != "fleet":
        return summary.loc[[], cols].reset_index(drop=True)
    rows = (
        summary["model"].isin(cfg.robust_models).to_numpy(bool)
        if cfg.robust_models
        else np.ones(len(summary), bool)
    )
    return summary.loc[rows, cols].reset_index(drop=True)


def pooled_scales(
    summary: pd.DataFrame, config: OutlierConfig | None = None
) -> dict[tuple[str, str], tuple[float, tuple[int, ...]]]:
    """(model, parameter) -> (pooled robust scale, sorted sizes of the lots pooled), the
    values :func:`flag_lots` uses for ``summary`` (empty with ``scale_pool="lot"``). A lot's
    flags and scores depend on the other lots only through these: a lot whose own rows are
    unchanged keeps its flags exactly as long as they are unchanged. ``summary`` may be
    :func:`pooling_rows` of the summary."""
    cfg = config or OutlierConfig()
    rows = pooling_rows(summary, cfg)
    rows["lot"] = rows["lot"].astype(str)  # as flag_lots compares lots
    return _lot_centred_scales(rows, cfg.min_units) if len(rows) else {}
