"""The thermal section of the reports (calibration over temperature, docs/thermal.md).

One builder with the sections' signature, ``build(ctx, page, unit)`` -> HTML or None:

- ``unit=None``: the lot's section: the spread of each thermal coefficient over the lot's
  units (median, robust sd, min, max) and its outliers (robust z beyond 3.5 or a failed
  limit) (each unit's plots are a part of its block, :data:`reports.sections.UNIT_SECTIONS`);
- a unit: its parameters against temperature: each session's estimate (with its standard
  error, heating and cooling apart), the fitted polynomial and its 95 % confidence band.

None when the lot (or unit) has no thermal calibration. The section computes no number: the
lot's spread and outliers are the re-flag's (``qa/<lot>.json``, ``thermal_spread``: made by
:func:`calib_core.models.thermal.lot_spread_records` from the flagged summary rows of the
model ``thermal``), a unit's curves are its latest calibration file's
(``metadata.thermal_fit.curves``, a gain's change from 25 degC included).
"""

from __future__ import annotations

from typing import Any

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


def _curves(ctx, unit: str) -> dict[str, Any] | None:
    hist = ctx.view.history(unit)
    for item in reversed(hist):
        fit = ((item["doc"].get("metadata") or {}).get("thermal_fit")) or {}
        if fit.get("curves"):
            return fit
    return None


def _lot_html(ctx, page) -> str | None:
    spread = (ctx.qa_lot or {}).get("thermal_spread")
    if not spread:
        return None
    body = [
        '<p class="note">Each coefficient of the polynomials in the sensor temperature (about '
        "25 degC), over the lot's units: median, robust sd (1.4826 MAD), range, and the units "
        "beyond 3.5 robust sd or outside a configured limit.</p>",
        table(
            ["coefficient", "unit", "units", "median", "robust sd", "min", "max", "outliers"],
            (
                [
                    f'<span class="mono">{esc(r["parameter"])}</span>',
                    esc(r["unit_of_measure"]),
                    str(r["n"]),
                    fmt(r["median"], sig=3),
                    fmt(r["robust_sd"], sig=2),
                    fmt(r["min"], sig=3),
                    fmt(r["max"], sig=3),
                    esc(", ".join(r["outliers"])),
                ]
                for r in spread
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
        # a gain is drawn as its change from 25 degC (stored with the curve), a bias as is
        gain = unit_label == "ppm"
        if gain and "change" not in c:
            continue  # a file written before the curves carried the change

        def scale(key, c=c, gain=gain):
            v = c["change"][key] if gain else (c["points"]["value"] if key == "value" else c[key])
            return [x * factor for x in v]

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
                    "y": [scale("value")[i] for i in idx],
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
                "y": scale("hi") + scale("lo")[::-1],
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
                "y": scale("fit"),
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
