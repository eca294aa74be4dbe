"""The noise section of the reports (docs/noise.md): each unit's measured noise model.

One builder with the sections' signature, ``build(ctx, page, unit)`` -> HTML or None:

- ``unit=None``: the lot's section: the Allan deviation curves of every unit, one figure
  per sensor (gyro, accelerometer) on log-log axes, the flagged units drawn in red over the
  others in grey; then the coefficients of each unit with their 95 % intervals, where they
  were measured (a recording or the static steps) and the noise flags with their reason;
- a unit: its coefficients and flags (a part of its block).

None when the lot (or unit) has no noise rows. Everything shown is a stored number: the
``noise`` rows (values, intervals, flags, lot medians, computed by
:mod:`calib_core.noise_fleet`) and the ``noise_allan`` rows (curves).
"""

from __future__ import annotations

import pandas as pd

from reports.html import esc, fmt, table

SENSORS = (("gyro", ("gx", "gy", "gz")), ("accel", ("ax", "ay", "az")))
SENSOR_TITLE = {"gyro": "Gyroscopes", "accel": "Accelerometers"}
DASHES = {"gx": "solid", "gy": "dash", "gz": "dot", "ax": "solid", "ay": "dash", "az": "dot"}
FLAGGED_COLOUR, OTHER_COLOUR = "#d62728", "rgba(90,90,90,0.45)"
SHOWN = ("white", "bias_instability", "random_walk", "quantization", "ramp")


def _rows(ctx, name: str, unit: str | None) -> pd.DataFrame | None:
    df = ctx.view.of(name, ctx.lot, unit)
    return df if df is not None and len(df) else None


def _flagged_units(noise: pd.DataFrame) -> list[str]:
    f = noise[noise["flagged"].fillna(False).astype(bool)] if "flagged" in noise else noise.iloc[0:0]
    return sorted({str(u) for u in f["unit"]})


def _figure(allan: pd.DataFrame, channels, flagged: set[str], title: str) -> dict:
    data = []
    rows = allan[allan["channel"].isin(channels)]
    # the others first, the flagged units drawn over them
    for flag in (False, True):
        for (u, ch), r in rows.groupby(["unit", "channel"], sort=True):
            if (str(u) in flagged) != flag:
                continue
            r = r.sort_values("tau_s")
            colour = FLAGGED_COLOUR if flag else OTHER_COLOUR
            data.append(
                {
                    "type": "scatter",
                    "mode": "lines+markers",
                    "name": f"{u} {ch}" + (" (flagged)" if flag else ""),
                    "legendgroup": str(u),
                    "x": r["tau_s"].tolist(),
                    "y": r["adev"].tolist(),
                    "line": {"color": colour, "width": 2.5 if flag else 1, "dash": DASHES.get(ch, "solid")},
                    "marker": {"size": 4 if flag else 2, "color": colour},
                    "meta": {"unit": str(u), "flagged": flag},
                    "hovertemplate": f"{esc(u)} {ch}<br>tau %{{x:.3g}} s<br>adev %{{y:.3g}}<extra></extra>",
                }
            )
    uom = next((str(x) for x in rows["unit_of_measure"].dropna()), "")
    return {
        "data": data,
        "layout": {
            "title": {"text": title},
            "xaxis": {"type": "log", "title": {"text": "cluster time tau (s)"}},
            "yaxis": {
                "type": "log",
                "title": {"text": f"Allan deviation ({uom})" if uom else "Allan deviation"},
            },
            "showlegend": len(data) <= 24,
        },
    }


def _interval(r) -> str:
    if pd.isna(r.value):
        return f'<span class="note">{esc(r.reason or "")}</span>'
    txt = f"{fmt(r.value, sig=3)} [{fmt(r.lo, sig=2)}, {fmt(r.hi, sig=2)}] {esc(r.unit_of_measure or '')}"
    if bool(r.flagged) if not pd.isna(r.flagged) else False:
        return f'<span class="flagged">{txt}</span>'
    return txt


def _coefficient_table(noise: pd.DataFrame) -> str:
    body = []
    rows = noise[noise["coefficient"].isin(SHOWN)]
    order = {c: i for i, c in enumerate(SHOWN)}
    rows = rows.assign(_o=rows["coefficient"].map(order)).sort_values(["unit", "channel", "_o"])
    for r in rows.itertuples():
        body.append(
            [
                esc(r.unit),
                esc(r.channel),
                esc(str(r.coefficient).replace("_", " ")),
                _interval(r),
                fmt(r.lot_median, sig=3),
                fmt(r.score, sig=3),
            ]
        )
    return table(
        ["unit", "channel", "coefficient", "value [95 % interval]", "lot median", "robust z"],
        body,
        text_cols=4,
    )


def _periodic_table(noise: pd.DataFrame) -> str:
    rows = noise[noise["coefficient"] == "periodic"]
    if not len(rows):
        return ""
    return "<h3>Periodic lines</h3>" + table(
        ["unit", "channel", "frequency (Hz)", "amplitude"],
        (
            [
                esc(r.unit),
                esc(r.channel),
                fmt(r.frequency_hz, sig=4),
                f"{fmt(r.value, sig=3)} {esc(r.unit_of_measure or '')}",
            ]
            for r in rows.sort_values(["unit", "channel"]).itertuples()
        ),
        text_cols=2,
    )


def _flags_html(noise: pd.DataFrame) -> str:
    f = noise[noise["flagged"].fillna(False).astype(bool)] if "flagged" in noise else noise.iloc[0:0]
    if not len(f):
        return "<p class=\"note\">No unit's noise is unlike its lot's or outside a configured limit.</p>"
    items = "".join(
        f'<li data-unit="{esc(r.unit)}"><b>{esc(r.unit)}</b>: {esc(r.flag_reason)}</li>'
        for r in f.itertuples()
    )
    return f'<ul class="noise-flags">{items}</ul>'


def _sources(noise: pd.DataFrame) -> str:
    by = noise.drop_duplicates("unit")[["unit", "source", "duration_s", "rate_hz"]]
    return table(
        ["unit", "measured on", "duration (s)", "rate (Hz)"],
        (
            [esc(r.unit), esc(r.source), fmt(r.duration_s, sig=4), fmt(r.rate_hz, sig=4)]
            for r in by.itertuples()
        ),
        text_cols=2,
    )


def build(ctx, page, unit: str | None) -> str | None:
    noise = _rows(ctx, "noise", unit)
    if noise is None:
        return None
    if unit is not None:
        return _flags_html(noise) + _coefficient_table(noise) + _periodic_table(noise)
    flagged = set(_flagged_units(noise))
    parts = [
        '<p class="note">Each unit\'s noise model (IEEE Std 952 / 1293 coefficients with 95 % '
        "intervals, docs/noise.md), measured on its static recording "
        '(<span class="mono">lot=L/unit=U/noise/</span>) or, without one, on its sessions\' static '
        "steps (only what short steps can determine). A unit is flagged when a coefficient is "
        "unlike the lot's (robust z of its log beyond the family-wise threshold) or outside a "
        "configured limit; flagged units are drawn in red.</p>",
        _flags_html(noise),
    ]
    allan = _rows(ctx, "noise_allan", None)
    if allan is not None:
        for sensor, channels in SENSORS:
            if allan["channel"].isin(channels).any():
                parts.append(
                    page.figure(
                        _figure(allan, channels, flagged, f"{SENSOR_TITLE[sensor]}: Allan deviation by unit"),
                        height=420,
                        name=f"noise-allan-{sensor}",
                        caption="solid, dashed, dotted: x, y, z; red: units flagged for noise",
                    )
                )
    parts += [_sources(noise), "<h3>Coefficients</h3>", _coefficient_table(noise), _periodic_table(noise)]
    return "".join(parts)
