"""Unit report for an ad-hoc rerun: the unit's section of its lot report, the navigation
drift of its accelerometer calibration, and its calibration history.

``write_unit_report(results_root, unit)`` writes ``results_root/reports/units/<unit>.html``.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd

from calib_core.figure_statistics import changes_since_first
from reports import thermal_section
from reports.history import KEY_ELEMENTS, history_frame
from reports.html import (
    CASE_COLOURS,
    DASH,
    Page,
    arr,
    decimate,
    esc,
    fmt,
    fmt_time,
    grid,
    missing,
    table,
    write_atomic,
)
from reports.lot import ReportError, safe_name
from reports.sections import LotContext, kpi_block, qa_badge, unit_qa_note, unit_section
from reports.store import StoreView
from schemas.display import spread_unit

NAV_MAX_POINTS = 1500  # per trace; a 60 s drift at 1 kHz is 60,000 samples


def unit_report_path(results_root: str | Path, unit: str) -> Path:
    return Path(results_root) / "reports" / "units" / f"{safe_name(unit)}.html"


def navigation_figure(nav: pd.DataFrame) -> dict | None:
    if nav is None or not len(nav) or not {"case", "t"} <= set(nav.columns):
        return None
    panels = [c for c in ("vel_err", "pos_err") if c in nav.columns]
    if not panels:
        return None
    titles = {"vel_err": "velocity error [m/s]", "pos_err": "position error [m]"}
    layout, refs = grid(1, len(panels), [titles[p] for p in panels], hspace=0.08)
    found = {str(c) for c in nav["case"].unique()}
    cases = [c for c in ("none", "static", "static+dynamic") if c in found]
    cases += sorted(found - set(cases))
    # row positions per case, and only the columns drawn, as numpy (sub-frames of a 60,000-
    # sample trace with its string columns cost more than the decimation)
    by_case = {str(k): pos for k, pos in nav.groupby("case", sort=False).indices.items()}
    t_all = nav["t"].to_numpy(float)
    y_all = [nav[p].to_numpy(float) for p in panels]
    labels = {
        "none": "uncalibrated",
        "static": "static calibration",
        "static+dynamic": "static + dynamic (lever arms)",
    }
    data = []
    for case in cases:
        pos = by_case[case]
        t_case = t_all[pos]
        # in time order as DataFrame.sort_values("t") gives it: quicksort, NaN times last
        nan = np.isnan(t_case)
        ok = np.flatnonzero(~nan)
        pos = pos[np.concatenate([ok[t_case[ok].argsort(kind="quicksort")], np.flatnonzero(nan)])]
        t, ys = decimate(t_all[pos], [y[pos] for y in y_all], NAV_MAX_POINTS)
        for k, y in enumerate(ys):
            xr, yr = refs[k]
            data.append(
                {
                    "type": "scattergl" if len(t) > 5000 else "scatter",
                    "x": arr(t),
                    "y": arr(y),
                    "mode": "lines",
                    "name": labels.get(case, case),
                    "line": {"color": CASE_COLOURS.get(case, "#4c78a8"), "width": 1.6},
                    "legendgroup": case,
                    "showlegend": k == 0,
                    "xaxis": xr,
                    "yaxis": yr,
                }
            )
    for k in range(len(panels)):
        layout["xaxis" + refs[k][0][1:]].update(title={"text": "time [s]"})
    layout.update(
        legend={"orientation": "h", "y": 1.1, "x": 1, "xanchor": "right", "yanchor": "bottom"},
        margin={"t": 70, "b": 45, "l": 65, "r": 15},
    )
    return {"data": data, "layout": layout}


def history_figure(h: pd.DataFrame) -> dict | None:
    """Key parameters of every calibration file of the unit, as the change since its first
    calibration (scale factors in ppm, biases in their units): the elements of K differ by
    far more than they drift, so absolute values would draw flat lines."""
    if h is None or len(h) < 1:
        return None
    h = h.sort_values(["time", "produced"], kind="stable")
    groups = ["K_g", "w0", "K_a", "f0"]
    titles = {
        "K_g": "Gyroscope K<sub>g</sub> diagonal: change [ppm]",
        "w0": "Gyroscope bias ω<sub>0</sub>: change [deg/s]",
        "K_a": "Accelerometer K<sub>a</sub> diagonal: change [ppm]",
        "f0": "Accelerometer bias f<sub>0</sub>: change [mg]",
    }
    layout, refs = grid(2, 2, [titles[g] for g in groups], hspace=0.08, vspace=0.2)
    colours = ["#1f77b4", "#2ca02c", "#9467bd"]
    data = []
    t = [x.isoformat() for x in h["time"]]
    for k, g in enumerate(groups):
        xr, yr = refs[k]
        names = [e[1] for e in KEY_ELEMENTS if e[0] == g and (e[4] is None or e[3] == e[4])]
        # changes of the (dimensionless) K elements as spreads are shown: ppm
        scale = spread_unit("").factor if g.startswith("K") else 1.0
        unit = {"K_g": "", "K_a": "", "w0": " deg/s", "f0": " mg"}[g]
        changes = changes_since_first(h[names])
        for c, n in enumerate(names):
            v = h[n].to_numpy(float)
            data.append(
                {
                    "type": "scatter",
                    "x": t,
                    "y": arr(changes[n].to_numpy(float) * scale),
                    "mode": "lines+markers",
                    "name": n,
                    "marker": {"size": 7, "color": colours[c]},
                    "line": {"color": colours[c]},
                    "xaxis": xr,
                    "yaxis": yr,
                    "customdata": [f"{x:.6g}{unit}" for x in v],
                    "hovertemplate": f"{n} = %{{customdata}} (change %{{y:.3g}})<br>%{{x}}<extra></extra>",
                }
            )
        layout["xaxis" + xr[1:]].update(type="date", nticks=5)
    layout.update(
        showlegend=True,
        legend={"orientation": "v", "x": 1.02, "y": 1},
        margin={"t": 40, "b": 40, "l": 70, "r": 110},
        hovermode="closest",
    )
    return {"data": data, "layout": layout}


def history_table(h: pd.DataFrame) -> str:
    names = [e[1] for e in KEY_ELEMENTS if e[0] in ("w0", "f0")] + [
        "k_g11",
        "k_g22",
        "k_g33",
        "k_a11",
        "k_a22",
        "k_a33",
    ]
    heads = ["Acquired (UTC)", "Produced (UTC)", "QA", "Run id", "Code version", "File"] + [
        f"{n}{' [deg/s]' if n.startswith('w0') else ' [mg]' if n.startswith('f0') else ''}" for n in names
    ]
    rows = []
    for r in h.sort_values(["time", "produced"], ascending=False, kind="stable").itertuples():
        when = esc(fmt_time(r.time)) + (
            "" if r.time_source == "session_start" else " <small>(processing time: no session_start)</small>"
        )
        cells = [
            when,
            esc(fmt_time(r.produced)),
            qa_badge(r.qa_status),
            f'<span class="mono">{esc(r.run_id or DASH)}</span>',
            esc(r.code_version or DASH),
            f'<span class="mono">{esc(r.file)}</span>',
        ]
        for n in names:
            v = getattr(r, n)
            cells.append(fmt(v, 3 if n[0] in "wf" else 6))
        rows.append(cells)
    return table(heads, rows, cls="sortable", text_cols=6)


def render_unit_report(results_root: str | Path, unit: str, view: StoreView | None = None) -> str:
    """``view``: a StoreView of ``results_root`` to share its cached reads with other reports
    written in the same pass (a rerun writes the unit's report, then its lot's)."""
    view = view if view is not None else StoreView(results_root)
    lot = view.lot_of_unit(unit)
    if lot is None and not view.history(unit):
        raise ReportError(f"unit {unit!r} not found in results store {results_root}")
    page = Page(f"Unit {unit} · mimucal calibration report")
    body = []
    if lot is not None:
        ctx = LotContext.load(view, lot, unit=unit)
        body.append(
            f'<section id="summary"><h2>Summary</h2>{kpi_block(ctx, unit)}{unit_qa_note(ctx, unit)}</section>'
        )
        body.append(
            f'<section id="unit"><h2>Calibration of {esc(unit)}</h2>'
            + unit_section(ctx, page, unit, open_=True)
            + "</section>"
        )
        thermal = thermal_section.build(ctx, page, unit)  # calibration over temperature
        if thermal:
            body.append(f'<section id="thermal"><h2>Calibration over temperature</h2>{thermal}</section>')
    else:
        body.append(missing("Current results", "the unit has calibration files but no rows in the tables"))

    nav = view.of("navigation", lot, unit) if lot is not None else None
    if nav is None:
        nav_html = missing("Navigation drift", "navigation.parquet is absent")
    else:
        fig = navigation_figure(nav)
        nav_html = (
            page.figure(
                fig,
                height=360,
                name="navigation drift",
                caption=f"Strap-down drift replayed with each calibration; traces "
                f"downsampled to at most {NAV_MAX_POINTS} points (min/max kept).",
            )
            if fig is not None
            else '<p class="note">No navigation replay for this unit.</p>'
        )
    body.append(f'<section id="navigation"><h2>Navigation drift</h2>{nav_html}</section>')

    h = history_frame(view, [unit])
    if len(h) > 1:
        fig = history_figure(h)
        hist_html = (
            page.figure(fig, height=520, name="history")
            + f"<h3>Calibration files ({len(h)})</h3>"
            + history_table(h)
        )
    elif len(h) == 1:
        hist_html = (
            '<p class="note">One calibration so far: the history figure appears with the '
            "second one.</p>" + "<h3>Calibration files (1)</h3>" + history_table(h)
        )
    else:
        hist_html = missing("Calibration history", f"no files under calibrations/{unit}/")
    body.append(f'<section id="history"><h2>History of calibrations</h2>{hist_html}</section>')

    lot_link = f' · lot <a href="../{esc(safe_name(lot))}.html">{esc(lot)}</a>' if lot else ""
    header = (
        f'<header class="report"><h1>Unit {esc(unit)} · calibration report</h1>'
        f'<div class="sub">ad-hoc / rerun view{lot_link} · '
        '<a href="../index.html">fleet index</a></div></header>'
    )
    return page.render(header, "".join(body))


def write_unit_report(results_root: str | Path, unit: str, view: StoreView | None = None) -> Path:
    """Write ``results_root/reports/units/<unit>.html`` and return its path."""
    text = render_unit_report(results_root, unit, view)
    path = unit_report_path(results_root, unit)
    write_atomic(path, text)
    return path
