"""The key-parameter table: one table per key model, a row per unit."""

from __future__ import annotations

import pandas as pd

from calib_core.models.display import key_models as declared_key_models
from calib_core.models.display import ordered_params
from reports.context import (
    KIND_LIMITS,
    KIND_OUTLIER,
    LotContext,
    first_finite,
    flag_kinds,
    py_values,
    stored_column,
)
from reports.html import (
    DASH,
    Page,
    esc,
    missing,
    table,
)
from reports.sections.common import kind_badges, pretty_param


def key_models(ctx: LotContext) -> list[str]:
    present = {m for m, _ in ctx.params}
    return [m for m, _ in declared_key_models() if m in present]


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
    # the summary's columns as Python lists once (itertuples over a lot's rows is slow)
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
        title = dict(declared_key_models()).get(m, m)
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


def build(ctx: LotContext, page: Page, unit: str | None) -> str:
    """The key parameters of every unit of the lot."""
    return key_parameter_table(ctx)
