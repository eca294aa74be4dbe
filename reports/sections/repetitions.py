"""Per-unit tables: xu2016 Tables 1-2 (each repetition, average, spread) for every model, Table 3."""

from __future__ import annotations

import numpy as np

from calib_core.models.display import model_title
from reports.context import (
    LotContext,
)
from reports.html import (
    DASH,
    Page,
    esc,
    fmt,
    missing,
    table,
    td_numbers,
)
from reports.sections.common import pretty_param


def repetition_table(ctx: LotContext, unit: str, model: str) -> str:
    """xu2016 Table 1/2 layout: a row per parameter, a column per repetition, average, spread."""
    p = ctx.parameters
    if p is None:
        return missing(model_title(model), "parameters.parquet is absent")
    wide = ctx.rep_table(unit, model)
    if wide is None:
        return ""
    pnames, reps, V, S = wide
    names, order, infos = ctx.rep_layouts[(model, tuple(pnames))]
    heads = [
        f'<tr><td class="text">{pretty_param(n)}</td><td class="text">{esc(info.label) or DASH}</td>'
        for n, info in zip(names, infos)
    ]
    scale = np.array([info.scale for info in infos])[:, None]
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
    return f"<h4>{esc(model_title(model))}</h4>" + table(headers, rows, cls="paper", text_cols=2, wrap=False)


def compensation_table(ctx: LotContext, unit: str) -> str:
    """xu2016 Table 3 layout: input axis x method rows, output axis columns, min ~ max."""
    c = ctx.compensation
    if c is None:
        return missing("Table 3 (compensation errors)", "compensation.parquet is absent")
    cache = ctx.compensation_lookup
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


def build_key_tables(ctx: LotContext, page: Page, unit: str) -> str:
    """xu2016 Tables 1 and 2 of a unit side by side."""
    return (
        '<div class="grid2"><div>'
        + repetition_table(ctx, unit, "gyro")
        + "</div><div>"
        + repetition_table(ctx, unit, "accel")
        + "</div></div>"
    )


def build_compensation(ctx: LotContext, page: Page, unit: str) -> str:
    """xu2016 Table 3 of a unit."""
    return compensation_table(ctx, unit)


def build_other_models(ctx: LotContext, page: Page, unit: str) -> str | None:
    """The tables of a unit's other models, two a row (None when it has none)."""
    others = [repetition_table(ctx, unit, m) for m in ctx.unit_models(unit) if m not in ("gyro", "accel")]
    others = [o for o in others if o]
    if not others:
        return None
    return '<div class="grid2">' + "".join(f"<div>{o}</div>" for o in others) + "</div>"
