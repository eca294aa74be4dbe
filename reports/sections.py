"""Report sections shared by the lot and unit reports: header, key-parameter table,
strip plots across units, per-unit xu2016 Tables 1-3, residual plots, model discovery,
sessions. Every builder takes the rows of the results store it needs and returns HTML;
a missing table gives a visible "not available" note, never an exception."""

from __future__ import annotations

import math
from collections.abc import Iterable
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import pandas as pd

from calib_core.figure_statistics import compensation_envelope, residual_envelope, residual_rms
from reports.html import (
    CHANNEL_COLOURS,
    CLEAN,
    DASH,
    FLAGGED,
    LIMIT,
    MINUS,
    Page,
    arr,
    decimals_for,
    display_unit,
    esc,
    fmt,
    fmt_spread,
    fmt_time,
    grid,
    kpi,
    missing,
    spread_display,
    table,
    td_numbers,
    with_unit,
)
from reports.store import StoreView
from schemas.display import spread_unit

# Models in the key-parameter table and strip plots, with their headings.
KEY_MODELS: list[tuple[str, str]] = [
    (
        "gyro",
        "Gyroscope K<sub>g</sub>, ω<sub>0</sub> (ω = K<sub>g</sub> G + ω<sub>0</sub>: "
        "turntable multirate or field poses)",
    ),
    (
        "accel",
        "Accelerometer K<sub>a</sub>, f<sub>0</sub> (f = K<sub>a</sub> A + f<sub>0</sub>: "
        "turntable multiposition or field poses)",
    ),
    ("accel_static", "Accelerometer static model (zhang2017, 15 parameters)"),
    ("lever_arm", "Accelerometer lever arms (zhang2017 dynamic)"),
]
MODEL_TITLES = {
    "gyro": "Table 1 · gyroscope output model (multirate)",
    "accel": "Table 2 · accelerometer output model (multiposition)",
    "accel_static": "Accelerometer static model (zhang2017)",
    "lever_arm": "Accelerometer lever arms (zhang2017 dynamic)",
    "gyro_traditional": "Gyroscope, traditional inverse model",
    "accel_traditional": "Accelerometer, traditional inverse model",
}
_MAT = [f"{i}{j}" for i in (1, 2, 3) for j in (1, 2, 3)]
PARAM_ORDER = {
    "gyro": [f"k_g{m}" for m in _MAT] + ["w0_x", "w0_y", "w0_z"],
    "accel": [f"k_a{m}" for m in _MAT] + ["f0_x", "f0_y", "f0_z"],
    "lever_arm": [f"r{i}{a}" for i in (1, 2, 3) for a in "xyz"],
    # zhang2017: zero biases, scale factors, installation angles
    "accel_static": (
        [f"u0_{a}" for a in "xyz"]
        + [f"k_{a}" for a in "xyz"]
        + [f"theta_{a}{b}" for a in "xyz" for b in "xyz"]
    ),
    "gyro_traditional": [f"s_g{m}" for m in _MAT] + [f"b_g_{a}" for a in "xyz"],
    "accel_traditional": [f"s_a{m}" for m in _MAT] + [f"b_a_{a}" for a in "xyz"],
}


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


def pretty_param(name: str) -> str:
    n = str(name)
    for pre in ("k_g", "k_a", "s_g", "s_a"):
        if n.startswith(pre) and len(n) == len(pre) + 2:
            return f"{pre[0]}<sub>{pre[2]}{n[len(pre) :]}</sub>"
    for pre, html in (("w0_", "ω<sub>0"), ("f0_", "f<sub>0")):
        if n.startswith(pre):
            return f"{html}{n[len(pre) :]}</sub>"
    if len(n) == 3 and n[0] == "r" and n[1] in "123" and n[2] in "xyz":
        return f"r<sub>{n[1]}{n[2]}</sub>"
    return esc(n)


def ordered_params(model: str, names: Iterable[str]) -> list[str]:
    names = list(dict.fromkeys(str(n) for n in names))
    order = PARAM_ORDER.get(model, [])
    known = [n for n in order if n in names]
    return known + sorted(n for n in names if n not in order)


def ordered_models(models: Iterable[str]) -> list[str]:
    models = list(dict.fromkeys(str(m) for m in models))
    first = [m for m, _ in KEY_MODELS] + ["gyro_traditional", "accel_traditional"]
    return [m for m in first if m in models] + sorted(m for m in models if m not in first)


# ----------------------------------------------------------------------------- flag kinds

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
    if "[robust_z]" in text or "[spread]" in text:
        kinds.add(KIND_OUTLIER)
    return kinds


def kind_badges(kinds: set[str], count: int | None = None) -> str:
    """The badges of a unit or parameter: limits failed, outlier, or both."""
    n = f"{count} " if count else ""
    out = []
    if KIND_LIMITS in kinds:
        out.append(f'<span class="badge limit">✖ {n}limit failed</span>')
    if KIND_OUTLIER in kinds:
        out.append(f'<span class="badge flag">⚑ {"" if KIND_LIMITS in kinds else n}outlier</span>')
    return " ".join(out)


def qa_badge(status: Any) -> str:
    """The badge of a calibration file's QA status (pass / flagged / limits / not judged)."""
    if status == "pass":
        return '<span class="badge ok">pass</span>'
    if status == "flagged":
        return '<span class="badge flag">⚑ outlier</span>'
    if status == "limits":
        return '<span class="badge limit">✖ limits</span>'
    return '<span class="badge unjudged">not judged</span>'


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


# ----------------------------------------------------------------------------- lot context


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
        # group-by (pandas operations per group cost ~1 ms each, ~60 groups a lot)
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

    def unit_rows(self, name: str, unit: str) -> pd.DataFrame | None:
        """Rows of one unit from a table, grouped once per table (filtering a 50-unit lot's
        tables with a boolean mask per unit and per model costs seconds)."""
        cache = self.__dict__.setdefault("_by_unit", {})
        if name not in cache:
            df = getattr(self, name)
            cache[name] = None if df is None else {str(u): g for u, g in df.groupby("unit", sort=False)}
        groups = cache[name]
        if groups is None:
            return None
        df = getattr(self, name)
        return groups.get(unit, df.iloc[0:0])

    def rep_table(self, unit: str, model: str) -> tuple[list[str], list[int], np.ndarray, np.ndarray] | None:
        """(parameter names, repetitions, values, stderrs) of one unit and model, the arrays
        parameter x repetition; built for the whole lot with one unstack."""
        cache = self.__dict__.get("_rep_tables")
        if cache is None:
            cache = {}
            p = self.parameters
            if p is not None and len(p):
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
                        cache[keys[start]] = (
                            names[sl],
                            [r for r, h in zip(reps, have) if h],
                            V[sl][:, have],
                            S[sl][:, have],
                        )
                        start = k
            self.__dict__["_rep_tables"] = cache
        return cache.get((unit, model))

    def rep_stats(self, unit: str, model: str, names: list[str]) -> list[tuple[Any, Any, Any]]:
        """(mean, std, stderr of the mean) over the repetitions of each parameter ``names`` of
        one unit and model, in the stored unit: the unit's summary row (None when it has
        none)."""
        cache = self.__dict__.get("_summary_stats")
        if cache is None:
            cache = {}
            s = self.summary
            if s is not None and len(s):
                cols = [stored_column(s, c) for c in ("mean", "std", "stderr_of_mean")]
                keys = zip(py_values(s["unit"]), py_values(s["model"]), py_values(s["parameter"]))
                for i, key in enumerate(keys):
                    cache[tuple(map(str, key))] = tuple(c[i] for c in cols)
            self.__dict__["_summary_stats"] = cache
        none = (None, None, None)
        return [cache.get((unit, model, n), none) for n in names]

    def unit_models(self, unit: str) -> list[str]:
        cache = self.__dict__.get("_unit_models")
        if cache is None:
            self.rep_table(unit, "")
            found: dict[str, list[str]] = {}
            for u, m in self.__dict__["_rep_tables"]:
                found.setdefault(u, []).append(m)
            cache = self.__dict__["_unit_models"] = {u: ordered_models(ms) for u, ms in found.items()}
        return cache.get(unit, [])

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

    def _flag_index(self) -> dict[str, dict[str, set[str]]]:
        """unit -> model -> names of its flagged parameters, from the flagged summary rows
        once (reading them back per unit and per table costs ~1 ms a time in pandas)."""
        cache = self.__dict__.get("_flags_by_unit")
        if cache is None:
            cache = {}
            rows: dict[str, int] = {}
            f = self.flags
            if f is not None and len(f):
                for u, m, n in zip(py_values(f["unit"]), py_values(f["model"]), py_values(f["parameter"])):
                    cache.setdefault(str(u), {}).setdefault(m, set()).add(n)
                    rows[str(u)] = rows.get(str(u), 0) + 1
            self.__dict__["_flags_by_unit"] = cache
            self.__dict__["_flag_rows"] = rows
        return cache

    def n_param_flags(self, unit: str) -> int:
        """Flagged summary rows of a unit (0 when there is no summary)."""
        self._flag_index()
        return self.__dict__["_flag_rows"].get(unit, 0)

    def flagged_params(self, unit: str, model: str) -> set[str]:
        return self._flag_index().get(unit, {}).get(model, set())

    def session_counts(self, unit: str | None = None) -> dict[str, int]:
        s = self.sessions
        if s is None:
            return {}
        if unit is None:
            vc = s["status"].astype(str).value_counts()
            return {k: int(vc.get(k, 0)) for k in ("ok", "warned", "failed")}
        cache = self.__dict__.get("_session_counts")
        if cache is None:
            # one group-by for the lot instead of a value_counts per unit
            size = s.groupby([s["unit"], s["status"].astype(str)], sort=False).size()
            cache = {}
            for (u, st), n in size.items():
                cache.setdefault(str(u), {})[st] = int(n)
            self.__dict__["_session_counts"] = cache
        c = cache.get(unit, {})
        return {k: c.get(k, 0) for k in ("ok", "warned", "failed")}


# ----------------------------------------------------------------------------- header


def run_facts(ctx: LotContext) -> tuple[str, str, list[str]]:
    """(run time, run id(s), code version(s)) of the lot's current results."""
    run_ids: list[str] = []
    for df in (ctx.sessions, ctx.parameters):
        if df is not None and "run_id" in df and len(df):
            run_ids += [str(x) for x in df["run_id"].dropna().unique()]
    run_ids = list(dict.fromkeys(run_ids))
    times = [ctx.view.run(r)["_time"] for r in run_ids if ctx.view.run(r) and ctx.view.run(r)["_time"]]
    if times:
        when = fmt_time(max(times))
    elif (
        ctx.sessions is not None
        and "calibrated_at" in ctx.sessions
        and ctx.sessions["calibrated_at"].notna().any()
    ):
        when = fmt_time(str(ctx.sessions["calibrated_at"].dropna().astype(str).max()))
    else:
        when = "unknown"
    versions: list[str] = []
    if ctx.parameters is not None and "code_version" in ctx.parameters:
        versions = sorted({str(v) for v in ctx.parameters["code_version"].dropna().unique()})
    if not versions:
        for r in run_ids:
            doc = ctx.view.run(r)
            if doc and doc.get("code_version"):
                versions.append(str(doc["code_version"]))
    return when, ", ".join(run_ids[-3:]) + (" …" if len(run_ids) > 3 else ""), versions


def kpi_block(ctx: LotContext, unit: str | None = None) -> str:
    when, run_ids, versions = run_facts(ctx)
    counts = ctx.session_counts(unit)
    items = [kpi("Run time", esc(when)), kpi("Code version", esc(", ".join(versions) or "unknown"))]
    if counts:
        items += [
            kpi("Sessions ok", str(counts["ok"]), "good"),
            kpi("Warned", str(counts["warned"]), "warn" if counts["warned"] else ""),
            kpi("Failed", str(counts["failed"]), "bad" if counts["failed"] else ""),
        ]
    else:
        items.append(kpi("Sessions", "no sessions table"))
    if unit is None:
        n_flag = len(ctx.flagged_units)
        items += [
            kpi("Units", str(len(ctx.units))),
            kpi("Units flagged", f"{n_flag}", "bad" if n_flag else "good"),
        ]
    else:
        n = ctx.n_param_flags(unit)
        items.append(kpi("Flagged parameters", str(n), "bad" if n else "good"))
    extra = f'<p class="note">Run id: <span class="mono">{esc(run_ids or "unknown")}</span></p>'
    return f'<div class="kpis">{"".join(items)}</div>{extra}'


def flags_list(ctx: LotContext, unit: str | None = None, link: bool = True) -> str:
    f = ctx.flags if unit is None else ctx.unit_flags(unit)
    if ctx.summary is None:
        return missing("Outlier flags", "summary.parquet is absent")
    items = []
    for u, reason in sorted(ctx.unit_level_flags.items()):
        if unit is None or u == unit:
            ul = f'<a href="#unit-{esc(u)}">{esc(u)}</a>' if link else esc(u)
            items.append(
                f'<li data-unit="{esc(u)}">{kind_badges(flag_kinds(reason) or {KIND_OUTLIER})} '
                f"<b>{ul}</b> · {esc(reason)}</li>"
            )
    if (f is None or not len(f)) and not items:
        return '<p class="note">No parameter flagged.</p>'
    f = f if f is not None else ctx.summary.iloc[0:0]
    for r in f.sort_values(["unit", "model", "parameter"]).itertuples():
        p = ctx.info(r.model, r.parameter)
        u = f'<a href="#unit-{esc(r.unit)}">{esc(r.unit)}</a>' if link else esc(r.unit)
        med = getattr(r, "lot_median", np.nan)
        score = getattr(r, "score", np.nan)
        kinds = flag_kinds(getattr(r, "flag_reason", "")) or {KIND_OUTLIER}
        items.append(
            f'<li data-unit="{esc(r.unit)}" data-param="{esc(r.parameter)}" '
            f'data-kind="{esc(" ".join(sorted(kinds)))}">{kind_badges(kinds)} '
            f"<b>{u}</b> · {esc(r.model)} {pretty_param(r.parameter)} = "
            f"<b>{ctx.value(r.model, r.parameter, r.mean)}</b>{with_unit(p.label)} "
            f"(lot median {ctx.value(r.model, r.parameter, med)}, score {fmt(score, 1)}) · "
            f"{esc(getattr(r, 'flag_reason', '') or '')}</li>"
        )
    return f'<ul class="flags">{"".join(items)}</ul>'


def unit_qa_note(ctx: LotContext, unit: str) -> str:
    """The QA status of the unit's current calibration file (what ``mimucal calibration``
    hands out or refuses) with its reasons and the lot context it was judged in."""
    import json

    ut = ctx.unit_rows("units_table", unit) if ctx.units_table is not None else None
    rel = None if ut is None or not len(ut) else ut["calibration_file"].iloc[0]
    if not isinstance(rel, str) or not rel:
        return '<p class="note">No current calibration file.</p>'
    try:
        doc = json.loads((ctx.view.root / rel).read_text())
    except (OSError, ValueError) as exc:
        return f'<p class="note">QA status unreadable: {esc(exc)}</p>'
    qa = doc.get("qa") if isinstance(doc.get("qa"), dict) else None
    if qa is None:
        return (
            f'<p class="note qa-status">{qa_badge(None)} the current calibration '
            f'<span class="mono">{esc(rel)}</span> was not judged in a lot.</p>'
        )
    reasons = "".join(f"<li>{esc(r)}</li>" for r in qa.get("reasons") or [])
    return (
        f'<div class="qa-status"><p>{qa_badge(qa.get("status"))} QA status of the current '
        f'calibration <span class="mono">{esc(rel)}</span> in lot {esc(qa.get("lot"))} '
        f"({esc(qa.get('reference_detail') or qa.get('reference'))}; judged "
        f"{esc(fmt_time(qa.get('judged_at')) or DASH)})</p>"
        + (f'<ul class="flags">{reasons}</ul>' if reasons else "")
        + "</div>"
    )


def qa_reference_note(ctx: LotContext) -> str:
    """Which reference the lot's units were judged against (its own lot or the fleet
    history of earlier lots), the threshold and the limits in force."""
    qa = ctx.qa_lot or {}
    parts = []
    if qa:
        ref = {
            "lot": "the lot itself",
            "fleet history": "the fleet history",
            "none": "no reference (too few units, no fleet history)",
        }.get(qa.get("reference"), str(qa.get("reference")))
        parts.append(
            f"<b>Reference:</b> {esc(ref)}"
            + (f" ({esc(qa.get('reference_detail'))})" if qa.get("reference_detail") else "")
            + f"; |robust z| threshold {fmt(qa.get('z_threshold'), 2)}; judged "
            f"{esc(fmt_time(qa.get('judged_at')) or DASH)}."
        )
    else:
        parts.append("<b>Reference:</b> not recorded (the lot was not re-flagged by this version).")
    if ctx.limits:
        parts.append(
            f"<b>Limits:</b> {len(ctx.limits)} parameter(s) "
            + ", ".join(
                f"{esc(m)}.{esc(n)} ({esc(lim.written)})" for (m, n), lim in sorted(ctx.limits.items())
            )
            + "."
        )
    else:
        parts.append("<b>Limits:</b> none configured.")
    if ctx.limits_problem:
        parts.append(esc(ctx.limits_problem))
    return f'<p class="note qa-reference">{" ".join(parts)}</p>'


# ----------------------------------------------------------------------------- key table


def key_models(ctx: LotContext) -> list[str]:
    present = {m for m, _ in ctx.params}
    return [m for m, _ in KEY_MODELS if m in present]


def _flagged_cells(ctx: LotContext) -> dict[str, dict[str, set[str]]]:
    """model -> unit -> flagged parameters (from the summary's flagged rows)."""
    out: dict[str, dict[str, set[str]]] = {}
    f = ctx.flags
    if f is not None and len(f):
        for u, m, n in zip(py_values(f["unit"]), py_values(f["model"]), py_values(f["parameter"])):
            out.setdefault(str(m), {}).setdefault(str(u), set()).add(str(n))
    return out


def key_parameter_table(ctx: LotContext) -> str:
    """The key parameters, one table per model behind a chooser (tabs): a row per unit, the
    flagged units first, the unit column frozen; under each table the lot's median and its
    scatter (1.4826 MAD) in the spread's unit (ppm, deg/h, mg)."""
    s = ctx.summary
    if s is None or not len(s):
        return missing("Key-parameter table", "summary.parquet is absent or empty")
    models = key_models(ctx)
    if not models:
        return missing("Key parameters", "no gyro/accel/accel_static/lever_arm rows in summary.parquet")
    # the summary's columns as Python lists once (itertuples over ~3,000 rows costs ~40 ms)
    col = {c: py_values(s[c]) for c in ("mean", "std", "n_reps", "flagged", "flag_reason") if c in s}
    by_key = {
        k: i
        for i, k in enumerate(zip(py_values(s["unit"]), py_values(s["model"]), py_values(s["parameter"])))
    }
    no_flags = [False] * len(s)
    flag_cells = _flagged_cells(ctx)
    n_flags = {u: ctx.n_param_flags(u) + (u in ctx.unit_level_flags) for u in ctx.units}
    counts = {u: ctx.session_counts(u) for u in ctx.units}
    tabs, panels = [], []
    for k, m in enumerate(models):
        names = ordered_params(m, s.loc[s["model"] == m, "parameter"].unique())
        in_model = flag_cells.get(m, {})
        # flagged in this model first, then flagged elsewhere, then the rest; by unit id within
        units = sorted(ctx.units, key=lambda u: (not in_model.get(u), not n_flags[u], u))
        headers = ["Unit", "Sessions used/all", "Flags"]
        for n in names:
            p = ctx.info(m, n)
            headers.append(f"{pretty_param(n)}<br><small>{esc(p.label) or '&nbsp;'}</small>")
        rows = []
        for unit in units:
            c = counts[unit]
            n_all = sum(c.values()) if c else 0
            used = c.get("ok", 0) + c.get("warned", 0)
            cells = [
                f'<td class="text" data-sort="{esc(unit)}"><a href="#unit-{esc(unit)}">{esc(unit)}</a>'
                + (" " + kind_badges(ctx.unit_kinds.get(unit, {KIND_OUTLIER})) if n_flags[unit] else "")
                + "</td>",
                f'<td data-sort="{used}">{used}/{n_all}'
                + (f' <span class="badge failed">{c["failed"]} failed</span>' if c.get("failed") else "")
                + "</td>",
                f'<td data-sort="{n_flags[unit]}">{n_flags[unit] or ""}</td>',
            ]
            for n in names:
                i = by_key.get((unit, m, n))
                if i is None:
                    cells.append(f'<td data-sort="">{DASH}</td>')
                    continue
                p = ctx.info(m, n)
                mean, r_std = col["mean"][i], col["std"][i]
                val = ctx.value(m, n, mean)
                tip = (
                    f"{m} {n} = {val} {p.label} (spread over {col['n_reps'][i]} reps: "
                    f"{p.spread(r_std).replace(chr(160), ' ')})"
                )
                if bool(col.get("flagged", no_flags)[i]):
                    why = col["flag_reason"][i] if "flag_reason" in col else ""
                    kinds = flag_kinds(why) or {KIND_OUTLIER}
                    cls = "limit" if KIND_LIMITS in kinds else "flagged"
                    tip += f" — FLAGGED ({'limit failed' if cls == 'limit' else 'outlier'}): {why}"
                    cells.append(
                        f'<td class="{cls}" data-flagged="1" data-kind="{esc(" ".join(sorted(kinds)))}" '
                        f'data-param="{esc(n)}" data-sort="{float(mean)!r}" '
                        f'title="{esc(tip)}">{val}</td>'
                    )
                else:
                    cells.append(
                        f'<td data-param="{esc(n)}" data-sort="{float(mean)!r}" title="{esc(tip)}">{val}</td>'
                    )
            rows.append(({"class": "flagged-unit" if n_flags[unit] else "", "data-unit": unit}, cells))
        foot = _lot_rows(ctx, s, m, names)
        title = dict(KEY_MODELS).get(m, m)
        n_cells = sum(len(v) for v in in_model.values())
        badge = f' <span class="badge flag">{n_cells} ⚑</span>' if n_cells else ""
        tid = f"kp-{m}"
        tabs.append(
            f'<button type="button" role="tab" class="tab" id="{tid}-tab" aria-controls="{tid}" '
            f'aria-selected="{"true" if k == 0 else "false"}" data-tab="{tid}">{title}{badge}</button>'
        )
        panels.append(
            f'<div class="tabpanel" role="tabpanel" id="{tid}" data-model="{esc(m)}" '
            f'aria-labelledby="{tid}-tab"{"" if k == 0 else " hidden"}>'
            f'<h3 class="print-only">{title}</h3>'
            + table(
                headers,
                rows + foot,
                cls="sortable params key-parameters",
                text_cols=1,
                attrs=f' id="key-parameters-{esc(m)}"',
            )
            + "</div>"
        )
    note = (
        '<p class="note">Mean over repetitions per unit; one table per model (choose above). '
        "Flagged units come first; click a column heading to sort. Red cells (⚑) are statistical "
        "outliers, orange cells (✖) failed an acceptance limit; hover a cell for its spread over "
        "repetitions and the reason. "
        "Values: biases stored in g in mg, a blank unit means dimensionless. The last two rows: "
        "the lot median and its scatter (1.4826 × MAD), spreads in ppm (ratios), deg/h (gyro "
        "biases) or mg (accelerometer biases).</p>"
    )
    return (
        note
        + f'<div class="tabs" role="tablist" id="key-parameter-tabs">{"".join(tabs)}</div>'
        + "".join(panels)
    )


def _lot_rows(ctx: LotContext, s: pd.DataFrame, model: str, names: list[str]) -> list[str]:
    """The lot median and scatter (1.4826 MAD, from 3 units) rows under a key-parameter
    table: the summary's ``lot_median`` and ``lot_scatter``; they stay last when the table is
    sorted (the runtime sorts the rows without class "lotstat")."""
    sub = s[s["model"] == model]
    by_name = {str(k): pos for k, pos in sub.groupby("parameter", sort=False).indices.items()}
    medians, scatters = stored_column(sub, "lot_median"), stored_column(sub, "lot_scatter")
    med, mad = [], []
    for n in names:
        pos = by_name.get(n, [])
        med.append(f"<td>{ctx.value(model, n, first_finite(medians, pos))}</td>")
        mad.append(f"<td>{ctx.info(model, n).spread(first_finite(scatters, pos))}</td>")
    return [
        f'<tr class="lotstat"><td class="text">lot median</td><td></td><td></td>{"".join(med)}</tr>',
        f'<tr class="lotstat"><td class="text">lot scatter</td><td></td><td></td>{"".join(mad)}</tr>',
    ]


# ----------------------------------------------------------------------------- strip plots


def _jitter(i: int) -> float:
    # deterministic spread of points around the box (golden-ratio sequence)
    return ((i * 0.618034) % 1.0 - 0.5) * 0.5


def _legend_top(y: float = 1.0) -> dict:
    return {"orientation": "h", "y": y, "x": 1.0, "xanchor": "right", "yanchor": "bottom"}


def strip_figure(ctx: LotContext, model: str) -> dict | None:
    """One panel per parameter: the box of every unit's mean (flagged ones included: the box
    is the lot as measured) and a point per unit; statistical outliers on that parameter as
    large red diamonds, limit failures as orange crosses, both labelled with the unit id;
    the acceptance limits of the parameter as dashed orange lines."""
    s = ctx.summary
    if s is None:
        return None
    sm = s[s["model"] == model]
    names = ordered_params(model, sm["parameter"].unique())
    if not names:
        return None
    ncols = min(6, len(names))
    nrows = math.ceil(len(names) / ncols)
    titles = []
    for n in names:
        p = ctx.info(model, n)
        titles.append(f"{pretty_param(n)}{' [' + p.label + ']' if p.label else ''}")
    layout, refs = grid(nrows, ncols, titles, hspace=0.055, vspace=0.3 / nrows)
    data: list[dict] = []
    shapes: list[dict] = []
    unit_index = {u: i for i, u in enumerate(ctx.units)}
    # the model's columns once, then each parameter's rows by position (pandas per parameter
    # costs ~1 ms a panel, 45 panels a lot)
    by_name = {str(k): pos for k, pos in sm.groupby("parameter", sort=False).indices.items()}
    mean_all = sm["mean"].to_numpy(dtype=float)
    flagged_all = (
        sm["flagged"].fillna(False).astype(bool).to_numpy() if "flagged" in sm else np.zeros(len(sm), bool)
    )
    units_all = sm["unit"].astype(str).to_numpy()
    reasons_all = (
        sm["flag_reason"].astype(str).to_numpy() if "flag_reason" in sm else np.array([""] * len(sm), object)
    )
    limit_all = np.array(["[limit]" in r for r in reasons_all], bool) & flagged_all
    any_limit_line = False
    for k, n in enumerate(names):
        xr, yr = refs[k]
        pos = by_name[n]
        p = ctx.info(model, n)
        vals = mean_all[pos] * p.scale
        flagged = flagged_all[pos]
        at_limit = limit_all[pos]
        outlier = flagged & ~at_limit
        units = units_all[pos]
        x = np.array([_jitter(unit_index.get(u, i)) for i, u in enumerate(units)])
        hover = np.array([f"{u}<br>{n} = {fmt(v, p.decimals)} {p.label}" for u, v in zip(units, vals)])
        data.append(
            {
                "type": "box",
                "y": arr(vals),
                "x0": 0,
                "name": "lot (all units)",
                "boxpoints": False,
                "marker": {"color": "#9fb3c8"},
                "fillcolor": "rgba(159,179,200,0.25)",
                "line": {"width": 1},
                "width": 0.8,
                "hoverinfo": "skip",
                "showlegend": False,
                "xaxis": xr,
                "yaxis": yr,
            }
        )
        data.append(
            {
                "type": "scatter",
                "x": arr(x[~flagged]),
                "y": arr(vals[~flagged]),
                "mode": "markers",
                "marker": {"color": CLEAN, "size": 6, "opacity": 0.85},
                "name": "unit (in family)",
                "text": list(hover[~flagged]),
                "hoverinfo": "text",
                "showlegend": k == 0,
                "legendgroup": "clean",
                "xaxis": xr,
                "yaxis": yr,
            }
        )
        for sel, name, colour, symbol, edge in (
            (outlier, "outlier", FLAGGED, "diamond", "#7f1d1d"),
            (at_limit, "limit failed", LIMIT, "x", "#7c2d12"),
        ):
            if not sel.any():
                continue
            reasons = reasons_all[pos][sel]
            data.append(
                {
                    "type": "scatter",
                    "x": arr(x[sel]),
                    "y": arr(vals[sel]),
                    "mode": "markers+text",
                    "name": name,
                    "marker": {
                        "color": colour,
                        "size": 12,
                        "symbol": symbol,
                        "line": {"color": edge, "width": 1},
                    },
                    "text": list(units[sel]),
                    "textposition": "middle right",
                    "textfont": {"color": colour, "size": 12},
                    "hovertext": [f"{h}<br><b>{name}</b>: {r}" for h, r in zip(hover[sel], reasons)],
                    "hoverinfo": "text",
                    "showlegend": False,
                    "legendgroup": name,
                    "cliponaxis": False,
                    "xaxis": xr,
                    "yaxis": yr,
                }
            )
        lim = ctx.limits.get((model, n))
        if lim is not None:
            for bound in (lim.min, lim.max):
                if bound is None:
                    continue
                any_limit_line = True
                y = float(bound) * p.scale
                shapes.append(
                    {
                        "type": "line",
                        "xref": xr,
                        "yref": yr,
                        "x0": -0.6,
                        "x1": 1.0,
                        "y0": y,
                        "y1": y,
                        "line": {"color": LIMIT, "width": 1.5, "dash": "dash"},
                    }
                )
                # an invisible point at the limit keeps it inside the autoranged axis
                data.append(
                    {
                        "type": "scatter",
                        "x": [0.95],
                        "y": [y],
                        "mode": "markers",
                        "marker": {"opacity": 0},
                        "hoverinfo": "text",
                        "text": [
                            f"limit {'min' if bound is lim.min else 'max'} {fmt(y, p.decimals)} {p.label}"
                        ],
                        "showlegend": False,
                        "xaxis": xr,
                        "yaxis": yr,
                    }
                )
        ax = "xaxis" + xr[1:]
        layout[ax].update(range=[-0.6, 1.0], showticklabels=False, showgrid=False, zeroline=False)
        layout["yaxis" + yr[1:]].update(
            tickformat=f".{max(p.decimals - 1, 0)}~f" if p.decimals is not None else "", nticks=5
        )
    # one legend entry per category even if the first panel has none
    data.append(
        {
            "type": "scatter",
            "x": [None],
            "y": [None],
            "mode": "markers",
            "name": "outlier (labelled)",
            "xaxis": "x",
            "yaxis": "y",
            "marker": {"color": FLAGGED, "size": 12, "symbol": "diamond"},
            "showlegend": True,
        }
    )
    data.append(
        {
            "type": "scatter",
            "x": [None],
            "y": [None],
            "mode": "markers",
            "name": "limit failed (labelled)",
            "xaxis": "x",
            "yaxis": "y",
            "marker": {"color": LIMIT, "size": 12, "symbol": "x"},
            "showlegend": True,
        }
    )
    if any_limit_line:
        data.append(
            {
                "type": "scatter",
                "x": [None],
                "y": [None],
                "mode": "lines",
                "name": "acceptance limit",
                "xaxis": "x",
                "yaxis": "y",
                "line": {"color": LIMIT, "dash": "dash"},
                "showlegend": True,
            }
        )
    layout.update(
        margin={"l": 60, "r": 20, "t": 50, "b": 20},
        hovermode="closest",
        legend={**_legend_top(), "y": 1.0 + 0.25 / nrows / 1.5},
    )
    if shapes:
        layout["shapes"] = [*layout.get("shapes", []), *shapes]
    return {"data": data, "layout": layout}


# ----------------------------------------------------------------------------- per unit tables


def repetition_table(ctx: LotContext, unit: str, model: str) -> str:
    """xu2016 Table 1/2 layout: a row per parameter, a column per repetition, average, spread."""
    p = ctx.parameters
    if p is None:
        return missing(MODEL_TITLES.get(model, model), "parameters.parquet is absent")
    wide = ctx.rep_table(unit, model)
    if wide is None:
        return ""
    pnames, reps, V, S = wide
    # row order, display facts and the two text cells of each row: the same for every unit
    # with the same parameters, so worked out once per model and parameter list
    layouts = ctx.__dict__.setdefault("_rep_layouts", {})
    layout = layouts.get((model, tuple(pnames)))
    if layout is None:
        names = ordered_params(model, pnames)
        row_of = {n: i for i, n in enumerate(pnames)}
        infos = [ctx.info(model, n) for n in names]
        heads = [
            f'<tr><td class="text">{pretty_param(n)}</td><td class="text">{esc(info.label) or DASH}</td>'
            for n, info in zip(names, infos)
        ]
        layout = layouts[(model, tuple(pnames))] = (
            names,
            [row_of[n] for n in names],
            infos,
            heads,
            np.array([info.scale for info in infos])[:, None],
        )
    names, order, infos, heads, scale = layout
    flagged = ctx.flagged_params(unit, model)
    headers = (
        ["Parameter", "Unit"] + [f"Rep {r}" for r in reps] + ["Average", "Spread (std)", "Stderr of average"]
    )
    Vs = V[order] * scale
    stats = ctx.rep_stats(unit, model, names)
    rows = []
    values, finite = Vs.tolist(), np.isfinite(Vs).tolist()
    for k, (n, info) in enumerate(zip(names, infos)):
        # the row as html.table would write it (two text cells, numbers right-aligned)
        cls = "avg flagged" if n in flagged else "avg"
        rows.append(
            heads[k]
            + td_numbers(values[k], finite[k], info.decimals)
            + f'<td class="{cls}">{ctx.value(model, n, stats[k][0])}</td>'
            # spreads in their own units (ppm, deg/h, mg)
            f'<td class="spread">{info.spread(stats[k][1])}</td>'
            f'<td class="spread">{info.spread(stats[k][2])}</td></tr>'
        )
    return f"<h4>{esc(MODEL_TITLES.get(model, model))}</h4>" + table(
        headers, rows, cls="paper", text_cols=2, wrap=False
    )


def compensation_table(ctx: LotContext, unit: str) -> str:
    """xu2016 Table 3 layout: input axis x method rows, output axis columns, min ~ max."""
    c = ctx.compensation
    if c is None:
        return missing("Table 3 (compensation errors)", "compensation.parquet is absent")
    cache = ctx.__dict__.get("_comp")
    if cache is None:
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
        # per unit: {(input, method, output): (lo, hi)} and the number of repetitions, read
        # out of the aggregate once (pandas row access per unit costs ~4 ms a unit)
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
        cache = {
            "lookup": lookups,
            "n_reps": n_reps_of,
            "uom": uom.to_dict(),
            "src": {u: ", ".join(sorted(v)) for u, v in src_sets.items()},
        }
        ctx.__dict__["_comp"] = cache
    lookup = cache["lookup"].get(unit)
    if not lookup:
        return '<p class="note">Table 3: no verification sweep for this unit.</p>'
    uom = str(cache["uom"].get(unit) or "deg/s")
    src = cache["src"].get(unit, "")
    n_reps = int(cache["n_reps"][unit])
    outs = sorted({k[2] for k in lookup})
    present = {k[1] for k in lookup}
    methods = [m for m in ("uncompensated", "proposed", "traditional") if m in present]
    methods += sorted(present - set(methods))
    rows = []
    for inp in sorted({k[0] for k in lookup}):
        for k, m in enumerate(methods):
            cells = [f"<b>{esc(inp)}</b>" if k == 0 else "", esc(m)]
            for o in outs:
                if (inp, m, o) in lookup:
                    lo, hi = lookup[(inp, m, o)]
                    cells.append(f"{fmt(lo, 3)} ~ {fmt(hi, 3)}")
                else:
                    cells.append(DASH)
            rows.append(({"class": "sep"} if k == 0 else {}, cells))
    return (
        "<h4>Table 3 · output errors of the angular rates ["
        + esc(uom)
        + "]</h4>"
        + table(
            ["Input axis", "Method"] + [f"{esc(o)}-axis output" for o in outs],
            rows,
            cls="paper",
            text_cols=2,
            wrap=False,
        )
        + f'<p class="note">Envelope (min ~ max) over {n_reps} repetition(s)'
        + f"{'; source: ' + esc(src) if src else ''}.</p>"
    )


# ----------------------------------------------------------------------------- residual plots


class ResidualIndex:
    """The aggregated residuals of a lot as numpy columns plus each unit's row positions,
    built once per report: per-unit figures then cost a few array takes instead of pandas
    filters, sorts and group-bys per unit (~35 ms a unit)."""

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


def residual_index(ctx: LotContext) -> ResidualIndex | None:
    if ctx.residual_agg is None:
        return None
    ri = ctx.__dict__.get("_residual_index")
    if ri is None:
        ri = ctx.__dict__["_residual_index"] = ResidualIndex(ctx.residual_agg)
    return ri


def _residual_figure(
    ri: ResidualIndex,
    d: np.ndarray,
    channels: tuple[str, ...],
    x_of,
    scale: float,
    unit: str,
    x_title: str,
    symbol: str,
    categorical: bool,
    x_axis: dict | None = None,
    hover_x_of=None,
) -> dict:
    """``d``: row positions in ``ri`` of one unit's points, in drawing order. ``x_axis``:
    settings of every x axis (e.g. symlog ticks); ``hover_x_of``: the x shown on hover when
    the drawn x is transformed."""
    model = ri.model[d]
    found = set(model)
    models = [m for m in ("baseline", "extended") if m in found] + sorted(found - {"baseline", "extended"})
    layout, refs = grid(1, len(models), [f"{m} model" for m in models], hspace=0.04, shared_y=True)
    data = []
    channel = ri.channel[d]
    for j, m in enumerate(models):
        xr, yr = refs[j]
        of_model = model == m
        for ch in channels:
            dc = d[of_model & (channel == ch)]
            if not len(dc):
                continue
            y = ri.residual[dc] * scale
            extra = {} if hover_x_of is None else {"customdata": hover_x_of(dc)}
            at = "%{x}" if hover_x_of is None else "%{customdata:.4g}"
            data.append(
                {
                    **extra,
                    "type": "scatter",
                    "x": x_of(dc),
                    "y": arr(y),
                    "mode": "markers",
                    "name": f"{ch} error",
                    "marker": {"color": CHANNEL_COLOURS[ch[1]], "size": 6, "symbol": symbol},
                    "error_y": {
                        "type": "data",
                        "symmetric": False,
                        "array": arr(ri.rmax[dc] * scale - y),
                        "arrayminus": arr(y - ri.rmin[dc] * scale),
                        "thickness": 1,
                        "width": 0,
                        "color": CHANNEL_COLOURS[ch[1]],
                    },
                    "legendgroup": ch,
                    "showlegend": j == 0,
                    "xaxis": xr,
                    "yaxis": yr,
                    "hovertemplate": f"{ch}: %{{y:.4g}} {unit} at {at}<extra>{m} model</extra>",
                }
            )
        layout["xaxis" + xr[1:]].update(title={"text": x_title}, **(x_axis or {}))
        if categorical:
            layout["xaxis" + xr[1:]].update(type="category", tickangle=-60, tickfont={"size": 10})
    layout["yaxis"].update(title={"text": f"error [{unit}]"}, zeroline=True)
    layout.update(legend=_legend_top(1.1), margin={"t": 70, "b": 90 if categorical else 45, "l": 65, "r": 15})
    return {"data": data, "layout": layout}


SYMLOG_LINEAR_DPS = 1.0  # the symlog rate axis is linear within +/- this rate, logarithmic beyond


def symlog(x: np.ndarray, c: float = SYMLOG_LINEAR_DPS) -> np.ndarray:
    """sign(x) log10(1 + |x|/c): a logarithmic axis for both signs and zero."""
    x = np.asarray(x, dtype=float)
    return np.sign(x) * np.log10(1.0 + np.abs(x) / c)


def symlog_axis(max_abs: float, c: float = SYMLOG_LINEAR_DPS) -> dict:
    """Tick values and labels of a symlog axis up to ``max_abs``: 0, +/-1, 10, 100... c."""
    decades = [c * 10**k for k in range(0, int(np.ceil(np.log10(max(max_abs, c) / c))) + 1)]
    vals = sorted({0.0, *decades, *(-d for d in decades)})
    return {
        "tickmode": "array",
        "tickvals": symlog(np.array(vals), c).tolist(),
        "ticktext": [f"{v:g}".replace("-", MINUS) for v in vals],
        "zeroline": True,
    }


def rates_span_decades(rates: np.ndarray, decades: float = 1.0) -> bool:
    """Whether the non-zero |rates| span at least ``decades`` decades (a linear axis would
    pile the low rates together)."""
    r = np.abs(np.asarray(rates, dtype=float))
    r = r[np.isfinite(r) & (r > 0)]
    return len(r) > 1 and r.max() / r.min() >= 10**decades


def gyro_residual_figure(ctx: LotContext, unit: str) -> dict | None:
    """Gyro error vs table rate; a symlog rate axis when the rates span a decade or more
    (the xu2016 protocol: 6 to 300 deg/s of both signs; a linear axis piles the low rates
    together)."""
    ri = residual_index(ctx)
    if ri is None:
        return None
    d = ri.select(unit, ri.is_gyro, ri.rate_dps)
    if d is None or not len(d):
        return None
    rates = ri.rate_dps[d]
    if rates_span_decades(rates):
        return _residual_figure(
            ri,
            d,
            ("gx", "gy", "gz"),
            lambda dc: arr(symlog(ri.rate_dps[dc])),
            1.0,
            "deg/s",
            "table rate [deg/s] (symmetric log scale)",
            "circle",
            False,
            x_axis=symlog_axis(float(np.nanmax(np.abs(rates)))),
            hover_x_of=lambda dc: ri.rate_dps[dc].tolist(),
        )
    return _residual_figure(
        ri,
        d,
        ("gx", "gy", "gz"),
        lambda dc: arr(ri.rate_dps[dc]),
        1.0,
        "deg/s",
        "table rate [deg/s]",
        "circle",
        False,
    )


def accel_residual_figure(ctx: LotContext, unit: str) -> dict | None:
    ri = residual_index(ctx)
    if ri is None:
        return None
    d = ri.select(unit, ri.is_accel, ri.step)
    if d is None or not len(d):
        return None

    def labels(dc: np.ndarray) -> list[str]:
        return [
            f"{u} up {h:g}°" if h == h else f"{u} up, step {int(st)}"
            for u, h, st in zip(ri.up_axis[dc], ri.angle_deg[dc].tolist(), ri.step[dc].tolist())
        ]

    label, scale = display_unit("g")  # residuals stored in g, shown in mg
    return _residual_figure(
        ri, d, ("ax", "ay", "az"), labels, scale, label, "orientation (axis up, heading)", "square", True
    )


def _unit_ticks(ctx: LotContext) -> list[str]:
    return [
        f"<span style='color:{FLAGGED}'><b>{u} ⚑</b></span>" if u in ctx.flagged_units else u
        for u in ctx.units
    ]


def residual_overview_figure(ctx: LotContext) -> dict | None:
    """RMS residual per unit and sensor, baseline vs extended model: one figure for the lot."""
    rms = residual_rms(ctx.residual_agg)
    if rms is None:
        return None
    units = ctx.units
    shown = {"gyro": display_unit("deg/s"), "accel": display_unit("g")}
    layout, refs = grid(
        1,
        2,
        [f"gyro RMS error [{shown['gyro'][0]}]", f"accelerometer RMS error [{shown['accel'][0]}]"],
        hspace=0.08,
    )
    styles = {
        "baseline": {"color": "#f58518", "symbol": "circle"},
        "extended": {"color": "#4c78a8", "symbol": "x"},
    }
    data = []
    for j, sensor in enumerate(("gyro", "accel")):
        scale = shown[sensor][1]
        xr, yr = refs[j]
        for m in sorted(rms["model"].astype(str).unique()):
            d = rms[(rms["sensor"] == sensor) & (rms["model"] == m)].set_index("unit").reindex(units)
            data.append(
                {
                    "type": "scatter",
                    "x": units,
                    "y": arr(d["rms"].to_numpy(float) * scale),
                    "mode": "markers",
                    "name": f"{m} model",
                    "marker": {"size": 8, **styles.get(m, {"color": "#54a24b", "symbol": "diamond"})},
                    "legendgroup": m,
                    "showlegend": j == 0,
                    "xaxis": xr,
                    "yaxis": yr,
                }
            )
        layout["xaxis" + xr[1:]].update(
            type="category", tickvals=units, ticktext=_unit_ticks(ctx), tickangle=-60
        )
        layout["yaxis" + yr[1:]].update(rangemode="tozero")
    layout.update(legend=_legend_top(1.1), margin={"t": 70, "b": 70, "l": 60, "r": 15})
    return {"data": data, "layout": layout}


# ----------------------------------------------------------------------------- discovery
# The discovery table holds one row per finding, its numbers already formatted in physical
# units (calib_core.discovery.presentation); the evidence table the series of each figure.

_DISC_KIND_ORDER = {"named": 0, "confounded": 1, "unexplained": 2, "partial": 3, "negligible": 4}
_DISC_KIND_TEXT = {
    "named": "Named effects (applied)",
    "confounded": "Confounded: the steps cannot tell these apart (combined fit applied, none named)",
    "unexplained": "Unexplained misfit (no catalogue effect accounts for it)",
    "partial": "Partial candidates (significant, leave their channels misfit; not applied)",
}


def _disc_rows(df: pd.DataFrame | None) -> pd.DataFrame:
    if df is None or not len(df) or "kind" not in df.columns:
        return pd.DataFrame()
    d = df[df["kind"].isin(list(_DISC_KIND_ORDER))].copy()
    d["_order"] = d["kind"].map(_DISC_KIND_ORDER)
    return d.sort_values(["_order", "unit", "effect"])


def _cell(v, sig: int | None = None) -> str:
    if v is None or (isinstance(v, float) and math.isnan(v)):
        return ""
    if sig is not None and isinstance(v, (float, np.floating, int, np.integer)):
        return f"{float(v):.{sig}g}"
    return esc(str(v))


def _lines(v, sep: str = "; ") -> str:
    """A text cell with one item per line: a confounded set's readings (`` | ``), and the
    items ``sep`` separates (kept at the end of the line: parameters, alternatives)."""
    text = _cell(v).replace(" | ", "<br>")
    return text.replace(esc(sep), esc(sep.rstrip()) + "<br>")


def _kind_table(rows: pd.DataFrame, kind: str, with_unit_col: bool) -> str:
    headers = (["Unit"] if with_unit_col else []) + [
        "Effects" if kind == "confounded" else "Effect",
        "Channels",
        "Estimate ± standard error",
        "Evidence",
        "Held-out rms before",
        "after (σ)",
        "gain",
    ]
    if kind == "confounded":
        headers.append("Steps that would separate them")
    body = []
    for r in rows.itertuples():
        cells = [f'<a href="#unit-{esc(r.unit)}">{esc(r.unit)}</a>'] if with_unit_col else []
        effect = str(r.effect).removeprefix("confounded: ") if kind == "confounded" else r.effect
        cells += [
            _lines(effect, ", "),
            _cell(r.channels),
            _lines(r.estimates),
            _cell(r.evidence),
            _cell(r.heldout_rms_before, 3),
            _cell(r.heldout_rms_after, 3),
            _cell(r.gain, 3),
        ]
        if kind == "confounded":
            # the step sets (the row's effects say what they separate)
            text = str(r.separated_by or "")
            cells.append(_lines(text.split("; add ", 1)[1] if "; add " in text else text, " or "))
        body.append(cells)
    return table(
        headers,
        body,
        cls=f"discovery {kind}",
        text_cols=len(headers) - 3 if kind != "confounded" else len(headers),
    )


def discovery_tables(df: pd.DataFrame | None, with_unit_col: bool) -> str:
    """Findings by kind (named, confounded, unexplained, partial), then the negligible
    terms in a folded list. Text cells only: no JSON."""
    d = _disc_rows(df)
    if not len(d):
        return ""
    out = []
    for kind, title in _DISC_KIND_TEXT.items():
        rows = d[d["kind"] == kind]
        if len(rows):
            out.append(f"<h4>{esc(title)}</h4>" + _kind_table(rows, kind, with_unit_col))
    neg = d[d["kind"] == "negligible"]
    if len(neg):
        items = "".join(
            f"<li>{(esc(r.unit) + ': ') if with_unit_col else ''}{esc(r.effect)} "
            f"({esc(r.estimates)}; held-out gain {_cell(r.gain, 3)})</li>"
            for r in neg.itertuples()
        )
        out.append(
            f'<details class="negligible"><summary>Negligible terms ({len(neg)}): '
            f"significant, but the unit fits without them or their held-out gain is "
            f"too small; not applied</summary><ul>{items}</ul></details>"
        )
    advice = sorted({a for a in d.get("advice", pd.Series(dtype=object)).dropna() if a})
    if advice:
        out.append(
            '<h4>Protocol advisor</h4><ul class="advice">'
            + "".join(f"<li>{esc(line)}</li>" for a in advice for line in a.split(" | "))
            + "</ul>"
        )
    return "".join(out)


def discovery_table(df: pd.DataFrame, with_unit_col: bool) -> str:
    return discovery_tables(df, with_unit_col)


def unit_discovery_table(ctx: LotContext, unit: str) -> str:
    """The findings of one unit ("" when it has none)."""
    d = ctx.discovery
    if d is None or not len(d):
        return ""
    return discovery_tables(d[d["unit"] == unit], with_unit_col=False)


def _evidence(ctx: LotContext) -> pd.DataFrame | None:
    if "_evidence" not in ctx.__dict__:
        ctx.__dict__["_evidence"] = ctx.view.of("discovery_evidence", ctx.lot)
    return ctx.__dict__["_evidence"]


def evidence_figures(ctx: LotContext, page: Page, unit: str) -> str:
    """For each named, confounded or unexplained finding of the unit, per channel: the
    baseline residual against the variable that drives it (every repetition), the fitted
    effect over it, and the residual after."""
    ev = _evidence(ctx)
    if ev is None or not len(ev):
        return ""
    u = ev[ev["unit"] == unit]
    out = []
    for (effect, channel), g in u.groupby(["effect", "channel"], sort=False):
        x = g["x"].to_numpy(float)
        order = np.argsort(x, kind="stable")
        first = g.iloc[0]
        xt = f"{first['x_label']}" + (f" ({first['x_unit']})" if first["x_unit"] else "")
        data = [
            {
                "type": "scatter",
                "mode": "markers",
                "x": arr(x),
                "y": arr(g["before"].to_numpy(float)),
                "name": "residual, affine model",
                "marker": {"color": "#f58518", "size": 5, "opacity": 0.7},
            },
            {
                "type": "scatter",
                "mode": "markers",
                "x": arr(x),
                "y": arr(g["after"].to_numpy(float)),
                "name": "residual after",
                "marker": {"color": "#4c78a8", "size": 5, "opacity": 0.7},
            },
        ]
        fitted = g["fitted"].to_numpy(float)
        if np.isfinite(fitted).any():
            data.insert(
                1,
                {
                    "type": "scatter",
                    "mode": "lines",
                    "x": arr(x[order]),
                    "y": arr(fitted[order]),
                    "name": "fitted effect",
                    "line": {"color": "#222", "width": 2},
                },
            )
        layout = {
            "legend": _legend_top(),
            "margin": {"t": 40, "b": 50, "l": 70, "r": 15},
            "xaxis": {"title": {"text": xt}},
            "yaxis": {"title": {"text": f"{channel} residual ({first['y_unit']})"}},
        }
        out.append(
            f"<h5>{esc(effect)} · {esc(channel)}</h5>"
            + page.figure(
                {"data": data, "layout": layout}, height=300, name=f"{unit} {effect} {channel} evidence"
            )
        )
    if not out:
        return ""
    return '<div class="evidence">' + "".join(out) + "</div>"


# ----------------------------------------------------------------------------- sessions


def as_text(v) -> str:
    """A store cell as text: lists/arrays of warnings joined, missing values empty."""
    if v is None:
        return ""
    if isinstance(v, (list, tuple, np.ndarray)):
        return "; ".join(str(x) for x in v)
    if isinstance(v, float) and math.isnan(v):
        return ""
    return str(v)


def sessions_section(ctx: LotContext, link_units: bool = True) -> str:
    s = ctx.sessions
    if s is None:
        return missing("Sessions", "sessions.parquet is absent")
    out = []
    failed = s[s["status"] == "failed"].sort_values(["unit", "rep"])
    if len(failed):
        rows = []
        for r in failed.itertuples():
            u = f'<a href="#unit-{esc(r.unit)}">{esc(r.unit)}</a>' if link_units else esc(r.unit)
            rows.append(
                (
                    {"data-unit": r.unit},
                    [
                        u,
                        str(r.rep),
                        f'<span class="mono">{esc(as_text(r.error_code))}</span>',
                        esc(as_text(r.message)),
                        f'<span class="mono">{esc(getattr(r, "path", ""))}</span>',
                    ],
                )
            )
        out.append(
            f"<h3>Failed sessions ({len(failed)})</h3>"
            + table(
                ["Unit", "Rep", "Error code", "Reason", "Session"], rows, cls="failed-sessions", text_cols=5
            )
        )
    else:
        out.append('<p class="note">No failed session.</p>')
    warned = s[s["status"] == "warned"].sort_values(["unit", "rep"])
    if len(warned):
        rows = [
            [esc(r.unit), str(r.rep), esc(as_text(getattr(r, "warnings", "")))] for r in warned.itertuples()
        ]
        out.append(
            f"<h3>Sessions with warnings ({len(warned)})</h3>"
            + table(["Unit", "Rep", "Warnings"], rows, cls="wrap", text_cols=3)
        )
    u = ctx.units_table
    if u is not None and len(u) and "state" in u:
        stale = u[u["state"].astype(str) != "calibrated"]
        if len(stale):
            rows = [[esc(r.unit), esc(r.state), esc(getattr(r, "reason", ""))] for r in stale.itertuples()]
            out.append(
                f"<h3>Units not freshly calibrated ({len(stale)})</h3>"
                + table(["Unit", "State", "Why"], rows, cls="wrap", text_cols=3)
            )
    return "".join(out)


# ----------------------------------------------------------------------------- unit section


def unit_section(ctx: LotContext, page: Page, unit: str, open_: bool = False) -> str:
    """The per-unit block of the lot report (and the body of the unit report)."""
    c = ctx.session_counts(unit)
    n_flags = ctx.n_param_flags(unit) + (unit in ctx.unit_level_flags)
    meta = []
    if c:
        meta.append(f"sessions ok {c['ok']}, warned {c['warned']}, failed {c['failed']}")
    badge = (
        kind_badges(ctx.unit_kinds.get(unit, {KIND_OUTLIER}), n_flags)
        if n_flags
        else '<span class="badge ok">in family</span>'
    )
    if c.get("failed"):
        badge += f' <span class="badge failed">{c["failed"]} failed session(s)</span>'
    parts = []
    if n_flags:
        parts.append(flags_list(ctx, unit, link=False))
    parts.append(
        '<div class="grid2"><div>'
        + repetition_table(ctx, unit, "gyro")
        + "</div><div>"
        + repetition_table(ctx, unit, "accel")
        + "</div></div>"
    )
    parts.append(compensation_table(ctx, unit))
    figs = []
    gf = gyro_residual_figure(ctx, unit)
    af = accel_residual_figure(ctx, unit)
    if gf is not None:
        figs.append(
            "<h4>Gyro error vs table rate (mean over repetitions, bars: min..max)</h4>"
            + page.figure(gf, height=330, name=f"{unit} gyro residuals")
        )
    if af is not None:
        figs.append(
            "<h4>Accelerometer error vs orientation (mean over repetitions, bars: min..max)</h4>"
            + page.figure(af, height=360, name=f"{unit} accel residuals")
        )
    if figs:
        parts.append("".join(figs))
    elif ctx.residuals is None:
        parts.append(missing("Residual plots", "residuals.parquet is absent"))
    others = [repetition_table(ctx, unit, m) for m in ctx.unit_models(unit) if m not in ("gyro", "accel")]
    others = [o for o in others if o]
    if others:
        parts.append('<div class="grid2">' + "".join(f"<div>{o}</div>" for o in others) + "</div>")
    if ctx.discovery is not None:
        dt = unit_discovery_table(ctx, unit)
        if dt:
            parts.append("<h4>Model discovery</h4>" + dt + evidence_figures(ctx, page, unit))
    if c.get("failed") and ctx.sessions is not None:
        f = ctx.unit_rows("sessions", unit)
        f = f[f["status"] == "failed"]
        parts.append(
            '<h4>Failed sessions</h4><ul class="flags">'
            + "".join(
                f'<li>rep {r.rep}: <span class="mono">{esc(r.error_code)}</span> {esc(r.message)}</li>'
                for r in f.itertuples()
            )
            + "</ul>"
        )
    return (
        f'<details class="unit" id="unit-{esc(unit)}" data-unit="{esc(unit)}"{" open" if open_ else ""}>'
        f'<summary>{esc(unit)} {badge}<span class="meta">{"; ".join(meta)}</span></summary>'
        f'<div class="body">{"".join(parts)}</div></details>'
    )
