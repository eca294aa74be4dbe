"""Lot report: one self-contained HTML file per lot, from the results store only.

``write_lot_report(results_root, lot)`` writes ``results_root/reports/<lot>.html``.
"""

from __future__ import annotations

from pathlib import Path

from reports.context import LotContext
from reports.html import Page, esc, write_atomic
from reports.sections import LOT_SECTIONS, render_sections
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
    body = render_sections(LOT_SECTIONS, ctx, page)
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
    return page.render(header, body)


def write_lot_report(results_root: str | Path, lot: str, view: StoreView | None = None) -> Path:
    """Write ``results_root/reports/<lot>.html`` and return its path."""
    text = render_lot_report(results_root, lot, view)
    path = lot_report_path(results_root, lot)
    write_atomic(path, text)
    return path
