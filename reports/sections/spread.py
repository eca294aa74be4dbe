"""Strip plots: each key parameter across the lot's units."""

from __future__ import annotations

import math

import numpy as np

from calib_core.models.display import key_models as declared_key_models
from calib_core.models.display import ordered_params
from reports.context import (
    LotContext,
)
from reports.html import (
    CLEAN,
    FLAGGED,
    LIMIT,
    Page,
    arr,
    fmt,
    grid,
    missing,
)
from reports.sections.common import legend_top, pretty_param
from reports.sections.parameters import key_models


def _jitter(i: int) -> float:
    # deterministic spread of points around the box (golden-ratio sequence)
    return ((i * 0.618034) % 1.0 - 0.5) * 0.5


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
    # the model's columns once, then each parameter's rows by position (a pandas selection
    # per parameter costs a lot's every panel)
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
        legend={**legend_top(), "y": 1.0 + 0.25 / nrows / 1.5},
    )
    if shapes:
        layout["shapes"] = [*layout.get("shapes", []), *shapes]
    return {"data": data, "layout": layout}


SPREAD_NOTE = (
    '<p class="note">Each point is one unit (mean over its repetitions); the box is the '
    "whole lot, flagged units included. Statistical outliers are red diamonds, limit "
    "failures orange crosses, both labelled with the unit; dashed orange lines are the "
    "acceptance limits.</p>"
)


def build(ctx: LotContext, page: Page, unit: str | None) -> str:
    """A strip plot per key model: each parameter across the lot's units."""
    strips = []
    for model in key_models(ctx):
        fig = strip_figure(ctx, model)
        if fig is not None:
            n = len({p for m, p in ctx.params if m == model})
            rows = -(-n // min(6, n))
            strips.append(
                f"<h3>{dict(declared_key_models())[model]}</h3>"
                + page.figure(fig, height=120 + 210 * rows, name=f"strip {model}")
            )
    return SPREAD_NOTE + ("".join(strips) or missing("Strip plots", "summary.parquet is absent"))
