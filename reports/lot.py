"""Lot report: one self-contained HTML file per lot, from the results store only.

``write_lot_report(results_root, lot)`` writes ``results_root/reports/<lot>.html``.
"""

from __future__ import annotations

from pathlib import Path

import pandas as pd

from reports import thermal_section
from reports.html import Page, esc, missing, write_atomic
from reports.sections import (
    KEY_MODELS,
    LotContext,
    discovery_table,
    flags_list,
    key_models,
    key_parameter_table,
    kpi_block,
    qa_reference_note,
    residual_overview_figure,
    sessions_section,
    strip_figure,
    unit_section,
)
from reports.store import StoreView


class ReportError(ValueError):
    """The store holds nothing about the requested lot or unit."""


def lot_report_path(results_root: str | Path, lot: str) -> Path:
    return Path(results_root) / "reports" / f"{safe_name(lot)}.html"


def safe_name(name: str) -> str:
    """File-name-safe version of a lot or unit id (ids come from directory names already,
    but a '/' must never escape the reports directory)."""
    return "".join(ch if ch.isalnum() or ch in "-_.=" else "_" for ch in str(name)) or "_"


def render_lot_report(results_root: str | Path, lot: str, view: StoreView | None = None) -> str:
    """``view``: a StoreView of ``results_root`` to share its cached reads with other reports
    written in the same pass."""
    view = view if view is not None else StoreView(results_root)
    if lot not in view.lots():
        known = ", ".join(view.lots()) or "none"
        raise ReportError(f"lot {lot!r} not found in results store {results_root} (lots: {known})")
    ctx = LotContext.load(view, lot)
    page = Page(f"Lot {lot} · mimucal calibration report")
    body = []
    body.append(
        f'<section id="summary"><h2>Summary</h2>{kpi_block(ctx)}'
        f"<h3>Flags: limit failures and outliers</h3>{qa_reference_note(ctx)}{flags_list(ctx)}</section>"
    )
    body.append(
        f'<section id="parameters"><h2>Key parameters by unit</h2>{key_parameter_table(ctx)}</section>'
    )

    strips = []
    for model in key_models(ctx):
        fig = strip_figure(ctx, model)
        if fig is not None:
            n = len({p for m, p in ctx.params if m == model})
            rows = -(-n // min(6, n))
            strips.append(
                f"<h3>{dict(KEY_MODELS)[model]}</h3>"
                + page.figure(fig, height=120 + 210 * rows, name=f"strip {model}")
            )
    body.append(
        '<section id="spread"><h2>Parameters across the lot</h2>'
        '<p class="note">Each point is one unit (mean over its repetitions); the box is the '
        "whole lot, flagged units included. Statistical outliers are red diamonds, limit "
        "failures orange crosses, both labelled with the unit; dashed orange lines are the "
        "acceptance limits.</p>"
        + ("".join(strips) or missing("Strip plots", "summary.parquet is absent"))
        + "</section>"
    )

    ov = residual_overview_figure(ctx)
    body.append(
        '<section id="residuals"><h2>Residuals across the lot</h2>'
        + (
            page.figure(
                ov,
                height=380,
                name="residual overview",
                caption="RMS over all steps and repetitions of the calibration tests; "
                "per-unit plots (error vs rate, error vs orientation) are in each unit's section.",
            )
            if ov is not None
            else missing("Residuals", "residuals.parquet is absent")
        )
        + "</section>"
    )

    if ctx.discovery is None:
        disc = missing("Model discovery", "discovery.parquet is absent (discovery not run)")
    elif not len(ctx.discovery):
        disc = '<p class="note">Model discovery ran and found no effect.</p>'
    else:
        d = ctx.discovery
        kind = d["kind"] if "kind" in d else pd.Series("", index=d.index)
        notes = [
            f"Model discovery ran for {d['unit'].nunique()} unit(s): "
            f"{d.loc[kind == 'named', 'unit'].nunique()} with a named effect, "
            f"{d.loc[kind == 'confounded', 'unit'].nunique()} with effects the steps cannot "
            f"tell apart, {d.loc[kind == 'unexplained', 'unit'].nunique()} with misfit left "
            f"unexplained. Held-out rms in units of the noise (σ); the evidence of each "
            f"finding (residual against what drives it) is in its unit's section."
        ]
        disc = f'<p class="note">{esc(" ".join(notes))}</p>' + discovery_table(d, with_unit_col=True)
    body.append(f'<section id="discovery"><h2>Model discovery</h2>{disc}</section>')
    thermal = thermal_section.build(ctx, page, None)  # calibration over temperature
    if thermal:
        body.append(f'<section id="thermal"><h2>Calibration over temperature</h2>{thermal}</section>')
    body.append(f'<section id="sessions"><h2>Sessions</h2>{sessions_section(ctx)}</section>')

    units_html = "".join(unit_section(ctx, page, u) for u in ctx.units)
    body.append(
        '<section id="units"><h2>Units</h2>'
        '<p class="note">Per unit: xu2016 Tables 1 and 2 (each repetition, average, spread), '
        "Table 3 (compensation errors), the other models, residual plots and discovery. "
        "Figures are drawn when a unit is opened.</p>"
        '<div class="toolbar"><button type="button" onclick="mimucalExpandAll(true)">Open all units</button> '
        '<button type="button" onclick="mimucalExpandAll(false)">Close all</button></div>'
        + units_html
        + "</section>"
    )

    n_flag = len(ctx.flagged_units)
    header = (
        f'<header class="report"><h1>Lot {esc(lot)} · calibration report</h1>'
        f'<div class="sub">{len(ctx.units)} units · {n_flag} flagged'
        + (
            ": " + ", ".join(f'<a href="#unit-{esc(u)}">{esc(u)}</a>' for u in ctx.flagged_units)
            if n_flag
            else ""
        )
        + ' · <a href="index.html">fleet index</a></div></header>'
    )
    return page.render(header, "".join(body))


def write_lot_report(results_root: str | Path, lot: str, view: StoreView | None = None) -> Path:
    """Write ``results_root/reports/<lot>.html`` and return its path."""
    text = render_lot_report(results_root, lot, view)
    path = lot_report_path(results_root, lot)
    write_atomic(path, text)
    return path
