"""Residual figures: the lot overview and each unit's gyro and accelerometer errors."""

from __future__ import annotations

import numpy as np

from calib_core.figure_statistics import residual_rms
from reports.context import (
    LotContext,
    ResidualIndex,
)
from reports.html import (
    CHANNEL_COLOURS,
    FLAGGED,
    MINUS,
    Page,
    arr,
    display_unit,
    grid,
    missing,
)
from reports.sections.common import legend_top


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
    layout.update(legend=legend_top(1.1), margin={"t": 70, "b": 90 if categorical else 45, "l": 65, "r": 15})
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
    ri = ctx.residual_index
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
    ri = ctx.residual_index
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
    layout.update(legend=legend_top(1.1), margin={"t": 70, "b": 70, "l": 60, "r": 15})
    return {"data": data, "layout": layout}


def build(ctx: LotContext, page: Page, unit: str | None) -> str:
    """The RMS residual of every unit, baseline and extended model."""
    ov = residual_overview_figure(ctx)
    if ov is None:
        return missing("Residuals", "residuals.parquet is absent")
    return page.figure(
        ov,
        height=380,
        name="residual overview",
        caption="RMS over all steps and repetitions of the calibration tests; "
        "per-unit plots (error vs rate, error vs orientation) are in each unit's section.",
    )


def build_unit(ctx: LotContext, page: Page, unit: str) -> str | None:
    """A unit's gyro error against the table rate and accelerometer error against the
    orientation (None when it has neither and the lot has residuals)."""
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
        return "".join(figs)
    if ctx.residuals is None:
        return missing("Residual plots", "residuals.parquet is absent")
    return None
