"""What a lot or unit report reads from the results store, read once: :class:`LotContext`.

``LotContext.load(view, lot, unit=None)`` reads the lot's tables (one unit's rows with
``unit``) and the display facts of each parameter; every view of the rows the sections need
(a unit's rows, the repetitions of a unit's model as an array, the flagged parameters, the
session counts, the residual index...) is a :func:`functools.cached_property`, worked out for
the whole lot the first time a section asks for it. The sections (``reports/sections/``)
format and draw; nothing here computes a number shown (``calib_core`` does, the store keeps
it)."""

from __future__ import annotations

import math
from collections.abc import Iterable
from dataclasses import dataclass, field
from functools import cached_property
from typing import Any

import numpy as np
import pandas as pd

from calib_core.figure_statistics import compensation_envelope, residual_envelope
from calib_core.models.display import ordered_models, ordered_params
from reports.html import DASH, decimals_for, display_unit, fmt, fmt_spread, spread_display
from reports.store import StoreView
from schemas.display import spread_unit


def py_values(x: pd.Series | pd.Index) -> list:
    """The elements of a Series or Index as Python objects, as ``list(x)`` gives them, without
    iterating an Arrow-backed string array element by element (~4 us an element)."""
    return x.to_numpy(dtype=object).tolist()


def stored_column(df: pd.DataFrame, name: str) -> list:
    """A stored numeric column as a list of floats (NaN where missing, all NaN when the
    table has no such column: a store written before it was stored)."""
    if name not in df:
        return [math.nan] * len(df)
    return df[name].to_numpy(dtype=float, na_value=math.nan).tolist()


def first_finite(values: list, positions: Iterable[int]) -> float:
    """The first finite ``values[i]`` for ``i`` in ``positions`` (a lot column repeats one
    value on each of its rows), NaN when none is."""
    return next((values[i] for i in positions if math.isfinite(values[i])), math.nan)


# Two separate categories: a failed acceptance limit (the engineer's limits file) and a
# statistical outlier (robust z or repetition spread against the lot or the fleet history).
KIND_OUTLIER = "outlier"


KIND_LIMITS = "limits"


def flag_kinds(reason: Any) -> set[str]:
    """The categories named by a stored ``flag_reason`` ("[limit] ...; [robust_z] ...")."""
    text = reason if isinstance(reason, str) else ""
    kinds = set()
    if "[limit]" in text:
        kinds.add(KIND_LIMITS)
    if "[robust_z]" in text or "[spread]" in text or "[noise]" in text:  # noise: calib_core.noise_fleet
        kinds.add(KIND_OUTLIER)
    return kinds


def as_text(v) -> str:
    """A store cell as text: lists/arrays of warnings joined, missing values empty."""
    if v is None:
        return ""
    if isinstance(v, (list, tuple, np.ndarray)):
        return "; ".join(str(x) for x in v)
    if isinstance(v, float) and math.isnan(v):
        return ""
    return str(v)


def stored_limits(view: StoreView) -> tuple[dict[tuple[str, str], Any], str]:
    """The acceptance limits of the store's QA configuration by (model, parameter), and a
    problem text ("" when none): a report never fails on the configuration."""
    try:
        text = view.store.read_qa_config()
        if text is None:
            return {}, ""
        from schemas.limits import config_from_toml

        cfg = config_from_toml(text, source=str(view.store.qa_config_path))
    except Exception as exc:  # noqa: BLE001 (shown in the report)
        return {}, f"limits not drawn: {exc}"
    return {(lim.model, lim.parameter): lim for lim in cfg.limits}, ""


@dataclass
class ParamInfo:
    """Display facts of one (model, parameter) across a lot."""

    model: str
    name: str
    uom: str
    label: str  # display unit of values
    scale: float  # display factor of values (g -> mg)
    decimals: int | None
    spread_label: str = ""  # display unit of spreads (ppm, deg/h, mg...: schemas.display)
    spread_scale: float = 1.0

    def spread(self, v: Any, sig: int = 2) -> str:
        """A spread in the stored unit as shown, e.g. "8.8 ppm"."""
        return fmt_spread(v, self.spread_scale, self.spread_label, sig)


@dataclass
class LotContext:
    """Everything a lot or unit report needs, read once from the store."""

    view: StoreView
    lot: str
    sessions: pd.DataFrame | None
    parameters: pd.DataFrame | None
    summary: pd.DataFrame | None
    units_table: pd.DataFrame | None
    residuals: pd.DataFrame | None
    compensation: pd.DataFrame | None
    discovery: pd.DataFrame | None
    units: list[str] = field(default_factory=list)
    params: dict[tuple[str, str], ParamInfo] = field(default_factory=dict)
    flags: pd.DataFrame | None = None  # flagged summary rows
    flagged_units: list[str] = field(default_factory=list)
    residual_agg: pd.DataFrame | None = None
    unit_level_flags: dict[str, str] = field(default_factory=dict)
    unit_kinds: dict[str, set[str]] = field(default_factory=dict)  # unit -> flag categories
    limits: dict[tuple[str, str], Any] = field(default_factory=dict)
    limits_problem: str = ""
    qa_lot: dict | None = None  # the lot's QA context (reference used, threshold, note)

    @classmethod
    def load(cls, view: StoreView, lot: str, unit: str | None = None) -> LotContext:
        ctx = cls(
            view=view,
            lot=lot,
            sessions=view.of("sessions", lot, unit),
            parameters=view.of("parameters", lot, unit),
            summary=view.of("summary", lot),
            units_table=view.of("units", lot),
            residuals=view.of("residuals", lot, unit),
            compensation=view.of("compensation", lot, unit),
            discovery=view.of("discovery", lot, unit),
        )
        units: set[str] = set()
        for df in (ctx.sessions, ctx.summary, ctx.units_table):
            if df is not None and len(df):
                units |= {str(u) for u in df["unit"].dropna().unique()}
        if unit is not None:
            units = {unit}
        ctx.units = sorted(units)
        ctx._param_info()
        if ctx.summary is not None and len(ctx.summary) and "flagged" in ctx.summary:
            f = ctx.summary[ctx.summary["flagged"].fillna(False).astype(bool)]
            ctx.flags = f
            ctx.flagged_units = sorted({str(u) for u in f["unit"]})
        ut = ctx.units_table
        if ut is not None and len(ut) and "flagged" in ut:
            # unit-level flags (e.g. repetition spread) that name no single parameter
            uf = ut[ut["flagged"].fillna(False).astype(bool)]
            ctx.unit_level_flags = {
                str(r.unit): as_text(getattr(r, "flag_reason", ""))
                for r in uf.itertuples()
                if str(r.unit) not in ctx.flagged_units
            }
            ctx.flagged_units = sorted(set(ctx.flagged_units) | set(ctx.unit_level_flags))
        if ut is not None and len(ut) and "flag_reason" in ut:
            for u, r, fl in zip(
                py_values(ut["unit"]),
                py_values(ut["flag_reason"]),
                py_values(ut["flagged"]) if "flagged" in ut else [None] * len(ut),
            ):
                if fl is not None and not pd.isna(fl) and bool(fl):
                    ctx.unit_kinds[str(u)] = flag_kinds(r) or {KIND_OUTLIER}
        if ctx.flags is not None:
            for u, r in zip(
                py_values(ctx.flags["unit"]),
                py_values(ctx.flags["flag_reason"]) if "flag_reason" in ctx.flags else [""] * len(ctx.flags),
            ):
                ctx.unit_kinds.setdefault(str(u), set()).update(flag_kinds(r) or {KIND_OUTLIER})
        ctx.limits, ctx.limits_problem = stored_limits(view)
        ctx.qa_lot = view.store.read_qa_lot(lot)
        ctx.residual_agg = residual_envelope(ctx.residuals)
        if ctx.summary is not None and len(ctx.summary) and not ctx.units:
            ctx.units = sorted({str(u) for u in ctx.summary["unit"].dropna()})
        return ctx

    def _param_info(self) -> None:
        src = self.summary if self.summary is not None and len(self.summary) else None
        if src is None and self.parameters is not None and len(self.parameters):
            src = self.parameters.rename(columns={"value": "mean"})
        if src is None:
            return
        # one pass over the columns as lists, positions per (model, parameter) from a single
        # group-by (pandas operations per group add up over a lot's groups)
        uoms = py_values(src["unit_of_measure"]) if "unit_of_measure" in src else None
        # decimals from the lot's typical repetition spread, else its scatter across units
        # (the summary's lot columns, written by the re-flag)
        typical = [stored_column(src, c) for c in ("lot_median_std", "lot_scatter")]
        for (model, name), pos in src.groupby(["model", "parameter"], sort=False).indices.items():
            uom = ""
            if uoms is not None:
                uom = next((str(uoms[i]) for i in pos if pd.notna(uoms[i])), "")
            label, scale = display_unit(uom)
            spread = next((v for v in (first_finite(col, pos) for col in typical) if v > 0), math.nan)
            dec = decimals_for(spread * scale, extra=1)
            slabel, sscale = spread_display(uom)
            self.params[(str(model), str(name))] = ParamInfo(
                str(model), str(name), uom, label, scale, dec, slabel, sscale
            )

    # ----------------------------------------------------------- views of the rows, once

    @staticmethod
    def _by_unit(df: pd.DataFrame | None) -> dict[str, pd.DataFrame] | None:
        return None if df is None else {str(u): g for u, g in df.groupby("unit", sort=False)}

    @cached_property
    def _sessions_by_unit(self) -> dict[str, pd.DataFrame] | None:
        return self._by_unit(self.sessions)

    @cached_property
    def _units_table_by_unit(self) -> dict[str, pd.DataFrame] | None:
        return self._by_unit(self.units_table)

    @cached_property
    def _flags_by_unit(self) -> dict[str, pd.DataFrame] | None:
        return self._by_unit(self.flags)

    def unit_rows(self, name: str, unit: str) -> pd.DataFrame | None:
        """Rows of one unit from a table (``sessions``, ``units_table`` or ``flags``), grouped
        once per table (filtering a 50-unit lot's tables with a boolean mask per unit and per
        model costs seconds)."""
        groups = getattr(self, f"_{name}_by_unit")
        if groups is None:
            return None
        df = getattr(self, name)
        return groups.get(unit, df.iloc[0:0])

    @cached_property
    def rep_tables(self) -> dict[tuple[str, str], tuple[list[str], list[int], np.ndarray, np.ndarray]]:
        """(unit, model) -> (parameter names, repetitions, values, stderrs), the arrays
        parameter x repetition; built for the whole lot with one unstack."""
        out: dict[tuple[str, str], tuple[list[str], list[int], np.ndarray, np.ndarray]] = {}
        p = self.parameters
        if p is None or not len(p):
            return out
        p = p.assign(
            rep=p["rep"].astype("int64"),
            unit=p["unit"].astype(str),
            model=p["model"].astype(str),
            parameter=p["parameter"].astype(str),
        )
        if "stderr" not in p:
            p = p.assign(stderr=np.nan)
        w = p.groupby(["unit", "model", "parameter", "rep"], sort=True)[["value", "stderr"]].last()
        w = w.unstack("rep")
        reps = [int(r) for r in w["value"].columns]
        V, S = w["value"].to_numpy(float), w["stderr"].to_numpy(float)
        idx = w.index
        keys = list(zip(py_values(idx.get_level_values(0)), py_values(idx.get_level_values(1))))
        names = [str(x) for x in py_values(idx.get_level_values(2))]
        have_all = np.isfinite(V)
        start = 0
        for k in range(1, len(keys) + 1):
            if k == len(keys) or keys[k] != keys[start]:
                sl = slice(start, k)
                have = have_all[sl].any(axis=0)  # repetitions this unit has
                out[keys[start]] = (
                    names[sl],
                    [r for r, h in zip(reps, have) if h],
                    V[sl][:, have],
                    S[sl][:, have],
                )
                start = k
        return out

    def rep_table(self, unit: str, model: str) -> tuple[list[str], list[int], np.ndarray, np.ndarray] | None:
        """(parameter names, repetitions, values, stderrs) of one unit and model."""
        return self.rep_tables.get((unit, model))

    @cached_property
    def rep_layouts(self) -> dict[tuple[str, tuple[str, ...]], tuple[list[str], list[int], list[ParamInfo]]]:
        """(model, its stored parameter names) -> (the names in display order, their rows in
        :meth:`rep_table`'s arrays, their display facts): the same for every unit with the
        same parameters, so worked out once per model and parameter list."""
        out: dict[tuple[str, tuple[str, ...]], tuple[list[str], list[int], list[ParamInfo]]] = {}
        for (_, model), (pnames, *_) in self.rep_tables.items():
            key = (model, tuple(pnames))
            if key not in out:
                names = ordered_params(model, pnames)
                row_of = {n: i for i, n in enumerate(pnames)}
                out[key] = (names, [row_of[n] for n in names], [self.info(model, n) for n in names])
        return out

    @cached_property
    def _summary_stats(self) -> dict[tuple[str, str, str], tuple[Any, Any, Any]]:
        out: dict[tuple[str, str, str], tuple[Any, Any, Any]] = {}
        s = self.summary
        if s is not None and len(s):
            cols = [stored_column(s, c) for c in ("mean", "std", "stderr_of_mean")]
            keys = zip(py_values(s["unit"]), py_values(s["model"]), py_values(s["parameter"]))
            for i, key in enumerate(keys):
                out[tuple(map(str, key))] = tuple(c[i] for c in cols)
        return out

    def rep_stats(self, unit: str, model: str, names: list[str]) -> list[tuple[Any, Any, Any]]:
        """(mean, std, stderr of the mean) over the repetitions of each parameter ``names`` of
        one unit and model, in the stored unit: the unit's summary row (None when it has
        none)."""
        none = (None, None, None)
        return [self._summary_stats.get((unit, model, n), none) for n in names]

    @cached_property
    def _unit_models(self) -> dict[str, list[str]]:
        found: dict[str, list[str]] = {}
        for u, m in self.rep_tables:
            found.setdefault(u, []).append(m)
        return {u: ordered_models(ms) for u, ms in found.items()}

    def unit_models(self, unit: str) -> list[str]:
        """The models of a unit's parameters, in their display order."""
        return self._unit_models.get(unit, [])

    def info(self, model: str, name: str) -> ParamInfo:
        ppm = spread_unit("")  # an unknown parameter: a dimensionless ratio
        return self.params.get((model, name)) or ParamInfo(
            model, name, "", "", 1.0, None, ppm.label, ppm.factor
        )

    def value(self, model: str, name: str, v: Any) -> str:
        p = self.info(model, name)
        try:
            return fmt(float(v) * p.scale, p.decimals)
        except (TypeError, ValueError):
            return DASH

    def unit_flags(self, unit: str) -> pd.DataFrame | None:
        if self.flags is None:
            return None
        return self.unit_rows("flags", unit)

    @cached_property
    def _flag_index(self) -> tuple[dict[str, dict[str, set[str]]], dict[str, int]]:
        """(unit -> model -> names of its flagged parameters, unit -> flagged rows), from the
        flagged summary rows once (reading them back per unit and per table in pandas adds
        up over a lot)."""
        by_unit: dict[str, dict[str, set[str]]] = {}
        rows: dict[str, int] = {}
        f = self.flags
        if f is not None and len(f):
            for u, m, n in zip(py_values(f["unit"]), py_values(f["model"]), py_values(f["parameter"])):
                by_unit.setdefault(str(u), {}).setdefault(m, set()).add(n)
                rows[str(u)] = rows.get(str(u), 0) + 1
        return by_unit, rows

    def n_param_flags(self, unit: str) -> int:
        """Flagged summary rows of a unit (0 when there is no summary)."""
        return self._flag_index[1].get(unit, 0)

    def flagged_params(self, unit: str, model: str) -> set[str]:
        return self._flag_index[0].get(unit, {}).get(model, set())

    @cached_property
    def _session_counts(self) -> dict[str, dict[str, int]]:
        """unit -> status -> sessions: one group-by for the lot instead of a value_counts per
        unit."""
        s = self.sessions
        size = s.groupby([s["unit"], s["status"].astype(str)], sort=False).size()
        out: dict[str, dict[str, int]] = {}
        for (u, st), n in size.items():
            out.setdefault(str(u), {})[st] = int(n)
        return out

    def session_counts(self, unit: str | None = None) -> dict[str, int]:
        s = self.sessions
        if s is None:
            return {}
        if unit is None:
            vc = s["status"].astype(str).value_counts()
            return {k: int(vc.get(k, 0)) for k in ("ok", "warned", "failed")}
        c = self._session_counts.get(unit, {})
        return {k: c.get(k, 0) for k in ("ok", "warned", "failed")}

    @cached_property
    def compensation_lookup(self) -> dict[str, dict] | None:
        """Table 3 of every unit read out of the compensation envelope once (pandas row
        access per unit would cost more than the unit's page): ``lookup`` unit -> {(input, method, output):
        (lo, hi)}, ``n_reps``, ``uom`` and ``src`` (its sources joined) by unit; None without a
        compensation table."""
        c = self.compensation
        if c is None:
            return None
        cc = c.assign(
            input_axis=c["input_axis"].astype(str),
            output_axis=c["output_axis"].astype(str),
            method=c["method"].astype(str),
        )
        agg = compensation_envelope(cc)
        uom = (
            cc.groupby("unit")["unit_of_measure"].first()
            if "unit_of_measure" in cc
            else pd.Series(dtype=object)
        )
        # per unit: its distinct sources, sorted and joined
        src_sets: dict[Any, set[str]] = {}
        if "source" in cc:
            pairs = cc[["unit", "source"]].dropna(subset=["source"]).drop_duplicates()
            for u, v in zip(py_values(pairs["unit"]), py_values(pairs["source"])):
                src_sets.setdefault(u, set()).add(str(v))
        lookups: dict[str, dict] = {}
        n_reps_of: dict[str, int] = {}
        idx = agg.index
        for u, inp, m, o, lo, hi, n in zip(
            *(py_values(idx.get_level_values(k)) for k in range(4)),
            agg["lo"].tolist(),
            agg["hi"].tolist(),
            agg["n_reps"].tolist(),
        ):
            lookups.setdefault(str(u), {})[(inp, m, o)] = (lo, hi)
            n_reps_of[str(u)] = max(n_reps_of.get(str(u), n), n)
        return {
            "lookup": lookups,
            "n_reps": n_reps_of,
            "uom": uom.to_dict(),
            "src": {u: ", ".join(sorted(v)) for u, v in src_sets.items()},
        }

    @cached_property
    def residual_index(self) -> ResidualIndex | None:
        """The lot's aggregated residuals as numpy columns (None without residuals)."""
        return None if self.residual_agg is None else ResidualIndex(self.residual_agg)

    @cached_property
    def evidence(self) -> pd.DataFrame | None:
        """The lot's discovery evidence series (None when the store has none)."""
        return self.view.of("discovery_evidence", self.lot)


class ResidualIndex:
    """The aggregated residuals of a lot as numpy columns plus each unit's row positions,
    built once per report: per-unit figures then cost a few array takes instead of pandas
    filters, sorts and group-bys per unit."""

    def __init__(self, a: pd.DataFrame) -> None:
        self.rows = {str(u): pos for u, pos in a.groupby("unit", sort=False).indices.items()}
        self.is_gyro = (
            ((a["test"] == "multirate") & a["channel"].isin(["gx", "gy", "gz"])).fillna(False).to_numpy(bool)
        )
        self.is_accel = (
            ((a["test"] == "multiposition") & a["channel"].isin(["ax", "ay", "az"]))
            .fillna(False)
            .to_numpy(bool)
        )
        self.model = a["model"].astype(str).to_numpy(object)
        self.channel = a["channel"].to_numpy(object)
        self.up_axis = a["up_axis"].astype(str).to_numpy(object)
        self.step = a["step"].to_numpy()
        self.angle_deg = a["angle_deg"].to_numpy(float)
        self.rate_dps = a["rate_dps"].to_numpy(float)
        self.residual = a["residual"].to_numpy(float)
        self.rmin = a["rmin"].to_numpy(float)
        self.rmax = a["rmax"].to_numpy(float)

    def select(self, unit: str, which: np.ndarray, by: np.ndarray) -> np.ndarray | None:
        """Row positions of a unit where ``which``, ordered by ``by`` as pandas
        ``sort_values`` orders them (numpy quicksort of the non-NaN values, NaNs last), so
        that the points come out in the same order as before."""
        pos = self.rows.get(unit)
        if pos is None:
            return None
        pos = pos[which[pos]]
        key = by[pos]
        nan = np.isnan(key) if key.dtype.kind == "f" else np.zeros(len(key), bool)
        ok = np.flatnonzero(~nan)
        order = np.concatenate([ok[key[ok].argsort(kind="quicksort")], np.flatnonzero(nan)])
        return pos[order]
