"""The sections of the lot and unit reports, in the order they appear.

Every section is a :class:`Section`: an id, a title and one builder
``build(ctx, page, unit) -> str | None`` (``ctx`` the :class:`reports.context.LotContext`,
``page`` the :class:`reports.html.Page` its figures go to, ``unit`` None for a lot section).
The builder returns the section's HTML, or None to leave it out; a table the store lacks
gives ``missing(...)``, never an exception.

- :data:`LOT_SECTIONS`: the lot report's sections, each written as ``<section id><h2>title``.
- :data:`UNIT_SECTIONS`: the parts of one unit's block (in the lot report's "Units" section and
  in the unit report), each under an ``<h4>`` title unless ``heading`` is False (the part
  writes its own headings).

Adding a section is a builder (a module of this package) and its line in one of the lists.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

from reports.context import KIND_OUTLIER, LotContext
from reports.html import Page, esc
from reports.sections import (
    discovery,
    noise,
    parameters,
    repetitions,
    residuals,
    sessions,
    spread,
    summary,
    thermal,
)
from reports.sections.common import kind_badges

Builder = Callable[[LotContext, Page, "str | None"], "str | None"]


@dataclass(frozen=True)
class Section:
    """One section: ``id`` (the HTML id of a lot section), ``title`` and its builder."""

    id: str
    title: str
    build: Builder
    heading: bool = True  # False: the builder writes its own headings (unit parts only)


# The parts of each unit's block, in order.
UNIT_SECTIONS: list[Section] = [
    Section("flags", "Flags", summary.build_unit_flags, heading=False),
    Section("tables", "Tables 1 and 2", repetitions.build_key_tables, heading=False),
    Section("compensation", "Table 3", repetitions.build_compensation, heading=False),
    Section("residuals", "Residual plots", residuals.build_unit, heading=False),
    Section("models", "Other models", repetitions.build_other_models, heading=False),
    Section("discovery", "Model discovery", discovery.build_unit),
    Section("thermal", "Calibration over temperature", thermal.build),
    Section("noise", "Noise", noise.build),
    Section("failed", "Failed sessions", sessions.build_unit_failed),
]


def unit_parts(ctx: LotContext, page: Page, unit: str) -> list[str]:
    """The HTML of each of :data:`UNIT_SECTIONS` a unit has, in order."""
    out = []
    for s in UNIT_SECTIONS:
        html = s.build(ctx, page, unit)
        if html is not None:
            out.append(f"<h4>{s.title}</h4>{html}" if s.heading else html)
    return out


def unit_section(ctx: LotContext, page: Page, unit: str, open_: bool = False) -> str:
    """The block of one unit (folded in the lot report, open in the unit report): its badges
    and session counts, then its parts."""
    c = ctx.session_counts(unit)
    n_flags = ctx.n_param_flags(unit) + (unit in ctx.unit_level_flags)
    meta = []
    if c:
        meta.append(f"sessions ok {c['ok']}, warned {c['warned']}, failed {c['failed']}")
    badge = (
        kind_badges(ctx.unit_kinds.get(unit, {KIND_OUTLIER}), n_flags)
        if n_flags
        else '<span class="badge ok">in family</span>'
    )
    if c.get("failed"):
        badge += f' <span class="badge failed">{c["failed"]} failed session(s)</span>'
    return (
        f'<details class="unit" id="unit-{esc(unit)}" data-unit="{esc(unit)}"{" open" if open_ else ""}>'
        f'<summary>{esc(unit)} {badge}<span class="meta">{"; ".join(meta)}</span></summary>'
        f'<div class="body">{"".join(unit_parts(ctx, page, unit))}</div></details>'
    )


UNITS_NOTE = (
    '<p class="note">Per unit: xu2016 Tables 1 and 2 (each repetition, average, spread), '
    "Table 3 (compensation errors), the other models, residual plots and discovery. "
    "Figures are drawn when a unit is opened.</p>"
    '<div class="toolbar"><button type="button" onclick="mimucalExpandAll(true)">Open all units</button> '
    '<button type="button" onclick="mimucalExpandAll(false)">Close all</button></div>'
)


def build_units(ctx: LotContext, page: Page, unit: str | None) -> str:
    """Every unit's block, folded."""
    return UNITS_NOTE + "".join(unit_section(ctx, page, u) for u in ctx.units)


# The lot report's sections, in order.
LOT_SECTIONS: list[Section] = [
    Section("summary", "Summary", summary.build),
    Section("parameters", "Key parameters by unit", parameters.build),
    Section("spread", "Parameters across the lot", spread.build),
    Section("residuals", "Residuals across the lot", residuals.build),
    Section("discovery", "Model discovery", discovery.build),
    Section("thermal", "Calibration over temperature", thermal.build),
    Section("noise", "Noise", noise.build),
    Section("sessions", "Sessions", sessions.build),
    Section("units", "Units", build_units),
]


def render_sections(sections: list[Section], ctx: LotContext, page: Page, unit: str | None = None) -> str:
    """The HTML of ``sections`` (a lot report's), each as ``<section id><h2>title``, the ones
    whose builder returns None left out."""
    out = []
    for s in sections:
        html = s.build(ctx, page, unit)
        if html is not None:
            out.append(f'<section id="{s.id}"><h2>{s.title}</h2>{html}</section>')
    return "".join(out)


__all__ = ["LOT_SECTIONS", "UNIT_SECTIONS", "Section", "render_sections", "unit_parts", "unit_section"]
