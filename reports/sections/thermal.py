"""The thermal section of the reports (calibration over temperature, docs/thermal.md).

One builder with the sections' signature, ``build(ctx, page, unit)`` -> HTML or None:

- ``unit=None``: the lot's section: the spread of each thermal coefficient over the lot's
  units (median, robust sd, min, max) and its outliers (robust z beyond 3.5 or a failed
  limit) (each unit's plots are a part of its block, :data:`reports.sections.UNIT_SECTIONS`);
- a unit: its parameters against temperature: each session's estimate (with its standard
  error, heating and cooling apart), the fitted polynomial and its 95 % confidence band.

None when the lot (or unit) has no thermal calibration. The numbers come from the store's
``summary`` rows of the model ``thermal`` and from the unit's latest calibration file
(``metadata.thermal_fit.curves``); the statistics are :func:`calib_core.models.thermal.
coefficient_spread`, computed there, not here.
"""

from __future__ import annotations

from typing import Any

import pandas as pd

from calib_core.models.thermal import coefficient_spread
from reports.html import esc, fmt, table
from schemas.display import Shown, spread_unit, value_unit

# Biases are shown as values (deg/s, mg); a gain's change from 25 degC is a small
# dimensionless change, shown as a spread is (ppm): the factors are schemas.display's.
GROUPS = (
    ("Gyro biases w0", ("w0_x", "w0_y", "w0_z"), value_unit("deg/s")),
    ("Accelerometer biases f0", ("f0_x", "f0_y", "f0_z"), value_unit("g")),
    ("Gyro gains K_g (diagonal), change from 25 degC", ("k_g11", "k_g22", "k_g33"), spread_unit("1")),
    (
        "Accelerometer gains K_a (diagonal), change from 25 degC",
        ("k_a11", "k_a22", "k_a33"),
        spread_unit("1"),
    ),
)
COLOURS = ("#1f77b4", "#d62728", "#2ca02c")


def _thermal_rows(ctx, unit: str | None = None) -> pd.DataFrame | None:
    s = ctx.summary
    if s is None or not len(s) or "model" not in s:
        return None
    rows = s[(s["model"] == "thermal") & s["parameter"].astype(str).str.contains("_tc")]
    if unit is not None:
        rows = rows[rows["unit"] == unit]
    return rows if len(rows) else None


def _curves(ctx, unit: str) -> dict[str, Any] | None:
    hist = ctx.view.history(unit)
    for item in reversed(hist):
        fit = ((item["doc"].get("metadata") or {}).get("thermal_fit")) or {}
        if fit.get("curves"):
            return fit
    return None


def _lot_html(ctx, page) -> str | None:
    rows = _thermal_rows(ctx)
    if rows is None:
        return None
    spread = coefficient_spread(
        pd.DataFrame(
            {
                "unit": rows["unit"],
                "parameter": rows["parameter"],
                "value": rows["mean"],
                "unit_of_measure": rows.get("unit_of_measure", ""),
                "flagged": rows.get("flagged", False),
            }
        )
    )
    body = [
        '<p class="note">Each coefficient of the polynomials in the sensor temperature (about '
        "25 degC), over the lot's units: median, robust sd (1.4826 MAD), range, and the units "
        "beyond 3.5 robust sd or outside a configured limit.</p>",
        table(
            ["coefficient", "unit", "units", "median", "robust sd", "min", "max", "outliers"],
            (
                [
                    f'<span class="mono">{esc(r.parameter)}</span>',
                    esc(r.unit_of_measure),
                    str(r.n),
                    fmt(r.median, sig=3),
                    fmt(r.robust_sd, sig=2),
                    fmt(r.min, sig=3),
                    fmt(r.max, sig=3),
                    esc(", ".join(r.outliers)),
                ]
                for r in spread.itertuples()
            ),
            text_cols=2,
        ),
    ]
    return "".join(body)


def _figure(curves: dict[str, Any], names, shown: Shown) -> dict:
    factor, unit_label = shown.factor, shown.label
    data = []
    for n, colour in zip(names, COLOURS):
        c = curves.get(n)
        if c is None:
            continue
        base = _at_25(c) if unit_label == "ppm" else 0.0  # a gain: its change from 25 degC

        def scale(v, base=base):
            return [(x - base) * factor for x in v]

        def rel(v):
            return [x * factor for x in v]

        pts = c["points"]
        for sweep, symbol, label in (
            (1, "triangle-up", "heating"),
            (-1, "triangle-down", "cooling"),
            (0, "circle", ""),
        ):
            idx = [i for i, s in enumerate(pts["sweep"]) if s == sweep]
            if not idx:
                continue
            data.append(
                {
                    "type": "scatter",
                    "mode": "markers",
                    "name": f"{n} {label}".strip(),
                    "x": [pts["temp_c"][i] for i in idx],
                    "y": scale([pts["value"][i] for i in idx]),
                    "error_y": {
                        "type": "data",
                        "array": rel([pts["stderr"][i] for i in idx]),
                        "visible": True,
                    },
                    "marker": {"symbol": symbol, "color": colour, "size": 7},
                    "legendgroup": n,
                }
            )
        data.append(
            {
                "type": "scatter",
                "mode": "lines",
                "name": f"{n} fit (order {c['order']})",
                "x": c["grid_c"] + c["grid_c"][::-1],
                "y": scale(c["hi"]) + scale(c["lo"])[::-1],
                "fill": "toself",
                "line": {"width": 0},
                "fillcolor": colour,
                "opacity": 0.2,
                "showlegend": False,
                "legendgroup": n,
                "hoverinfo": "skip",
            }
        )
        data.append(
            {
                "type": "scatter",
                "mode": "lines",
                "name": f"{n} fit (order {c['order']})",
                "x": c["grid_c"],
                "y": scale(c["fit"]),
                "line": {"color": colour},
                "legendgroup": n,
            }
        )
    return {
        "data": data,
        "layout": {
            "xaxis": {"title": {"text": "sensor temperature (degC)"}},
            "yaxis": {"title": {"text": unit_label}},
            "margin": {"l": 60, "r": 10, "t": 10, "b": 45},
            "legend": {"orientation": "v", "x": 1.02, "y": 1.0},
        },
    }


def _at_25(c: dict[str, Any]) -> float:
    """The fitted value nearest 25 degC (what a gain's change is counted from)."""
    grid = c["grid_c"]
    i = min(range(len(grid)), key=lambda k: abs(grid[k] - 25.0))
    return c["fit"][i]


def _unit_html(ctx, page, unit: str) -> str | None:
    fit = _curves(ctx, unit)
    if fit is None:
        return None
    curves = fit["curves"]
    parts = [
        f'<p class="note">Calibrated over {fmt(fit["range_c"][0], sig=3)}..{fmt(fit["range_c"][1], sig=3)} '
        f"degC (setpoints {', '.join(fmt(s, sig=3) for s in fit.get('setpoints_c', []))} degC). "
        "Markers: each session's estimate with its standard error (up: heating, down: "
        "cooling); line: the fitted polynomial; band: its 95 % confidence interval."
        + (
            f" Hysteresis named on {esc(', '.join(fit['hysteresis_named']))}: the line is the mid-line."
            if fit.get("hysteresis_named")
            else ""
        )
        + "</p>"
    ]
    for title, names, shown in GROUPS:
        fig = _figure(curves, names, shown)
        if fig["data"]:
            parts.append(
                f"<h4>{esc(title)}</h4>" + page.figure(fig, height=300, name=f"{unit} thermal {names[0]}")
            )
    warns = [w for w in fit.get("warnings", []) if w]
    if warns:
        parts.append('<ul class="flags">' + "".join(f"<li>{esc(w)}</li>" for w in warns) + "</ul>")
    return "".join(parts)


def build(ctx, page, unit: str | None = None) -> str | None:
    """The lot's thermal section (``unit`` None) or one unit's thermal plots; None when
    there is no thermal calibration to show."""
    if unit is None:
        return _lot_html(ctx, page)
    return _unit_html(ctx, page, unit)
