"""The summary: run facts, session counts, the flags list and the QA notes."""

from __future__ import annotations

import json

import numpy as np

from reports.context import (
    KIND_OUTLIER,
    LotContext,
    flag_kinds,
)
from reports.html import (
    DASH,
    Page,
    esc,
    fmt,
    fmt_time,
    kpi,
    missing,
    with_unit,
)
from reports.sections.common import kind_badges, pretty_param, qa_badge
from schemas.protocol_notes import lot_notes


def run_facts(ctx: LotContext) -> tuple[str, str, list[str]]:
    """(run time, run id(s), code version(s)) of the lot's current results."""
    run_ids: list[str] = []
    for df in (ctx.sessions, ctx.parameters):
        if df is not None and "run_id" in df and len(df):
            run_ids += [str(x) for x in df["run_id"].dropna().unique()]
    run_ids = list(dict.fromkeys(run_ids))
    times = [ctx.view.run(r)["_time"] for r in run_ids if ctx.view.run(r) and ctx.view.run(r)["_time"]]
    if times:
        when = fmt_time(max(times))
    elif (
        ctx.sessions is not None
        and "calibrated_at" in ctx.sessions
        and ctx.sessions["calibrated_at"].notna().any()
    ):
        when = fmt_time(str(ctx.sessions["calibrated_at"].dropna().astype(str).max()))
    else:
        when = "unknown"
    versions: list[str] = []
    if ctx.parameters is not None and "code_version" in ctx.parameters:
        versions = sorted({str(v) for v in ctx.parameters["code_version"].dropna().unique()})
    if not versions:
        for r in run_ids:
            doc = ctx.view.run(r)
            if doc and doc.get("code_version"):
                versions.append(str(doc["code_version"]))
    return when, ", ".join(run_ids[-3:]) + (" …" if len(run_ids) > 3 else ""), versions


def kpi_block(ctx: LotContext, unit: str | None = None) -> str:
    when, run_ids, versions = run_facts(ctx)
    counts = ctx.session_counts(unit)
    items = [kpi("Run time", esc(when)), kpi("Code version", esc(", ".join(versions) or "unknown"))]
    if counts:
        items += [
            kpi("Sessions ok", str(counts["ok"]), "good"),
            kpi("Warned", str(counts["warned"]), "warn" if counts["warned"] else ""),
            kpi("Failed", str(counts["failed"]), "bad" if counts["failed"] else ""),
        ]
    else:
        items.append(kpi("Sessions", "no sessions table"))
    if unit is None:
        n_flag = len(ctx.flagged_units)
        items += [
            kpi("Units", str(len(ctx.units))),
            kpi("Units flagged", f"{n_flag}", "bad" if n_flag else "good"),
        ]
    else:
        n = ctx.n_param_flags(unit)
        items.append(kpi("Flagged parameters", str(n), "bad" if n else "good"))
    extra = f'<p class="note">Run id: <span class="mono">{esc(run_ids or "unknown")}</span></p>'
    return f'<div class="kpis">{"".join(items)}</div>{extra}'


def flags_list(ctx: LotContext, unit: str | None = None, link: bool = True) -> str:
    f = ctx.flags if unit is None else ctx.unit_flags(unit)
    if ctx.summary is None:
        return missing("Outlier flags", "summary.parquet is absent")
    items = []
    for u, reason in sorted(ctx.unit_level_flags.items()):
        if unit is None or u == unit:
            ul = f'<a href="#unit-{esc(u)}">{esc(u)}</a>' if link else esc(u)
            items.append(
                f'<li data-unit="{esc(u)}">{kind_badges(flag_kinds(reason) or {KIND_OUTLIER})} '
                f"<b>{ul}</b> · {esc(reason)}</li>"
            )
    if (f is None or not len(f)) and not items:
        return '<p class="note">No parameter flagged.</p>'
    f = f if f is not None else ctx.summary.iloc[0:0]
    for r in f.sort_values(["unit", "model", "parameter"]).itertuples():
        p = ctx.info(r.model, r.parameter)
        u = f'<a href="#unit-{esc(r.unit)}">{esc(r.unit)}</a>' if link else esc(r.unit)
        med = getattr(r, "lot_median", np.nan)
        score = getattr(r, "score", np.nan)
        kinds = flag_kinds(getattr(r, "flag_reason", "")) or {KIND_OUTLIER}
        items.append(
            f'<li data-unit="{esc(r.unit)}" data-param="{esc(r.parameter)}" '
            f'data-kind="{esc(" ".join(sorted(kinds)))}">{kind_badges(kinds)} '
            f"<b>{u}</b> · {esc(r.model)} {pretty_param(r.parameter)} = "
            f"<b>{ctx.value(r.model, r.parameter, r.mean)}</b>{with_unit(p.label)} "
            f"(lot median {ctx.value(r.model, r.parameter, med)}, score {fmt(score, 1)}) · "
            f"{esc(getattr(r, 'flag_reason', '') or '')}</li>"
        )
    return f'<ul class="flags">{"".join(items)}</ul>'


def unit_qa_note(ctx: LotContext, unit: str) -> str:
    """The QA status of the unit's current calibration file (what ``mimucal calibration``
    hands out or refuses) with its reasons and the lot context it was judged in."""

    ut = ctx.unit_rows("units_table", unit) if ctx.units_table is not None else None
    rel = None if ut is None or not len(ut) else ut["calibration_file"].iloc[0]
    if not isinstance(rel, str) or not rel:
        return '<p class="note">No current calibration file.</p>'
    try:
        doc = json.loads((ctx.view.root / rel).read_text())
    except (OSError, ValueError) as exc:
        return f'<p class="note">QA status unreadable: {esc(exc)}</p>'
    qa = doc.get("qa") if isinstance(doc.get("qa"), dict) else None
    if qa is None:
        return (
            f'<p class="note qa-status">{qa_badge(None)} the current calibration '
            f'<span class="mono">{esc(rel)}</span> was not judged in a lot.</p>'
        )
    reasons = "".join(f"<li>{esc(r)}</li>" for r in qa.get("reasons") or [])
    return (
        f'<div class="qa-status"><p>{qa_badge(qa.get("status"))} QA status of the current '
        f'calibration <span class="mono">{esc(rel)}</span> in lot {esc(qa.get("lot"))} '
        f"({esc(qa.get('reference_detail') or qa.get('reference'))}; judged "
        f"{esc(fmt_time(qa.get('judged_at')) or DASH)})</p>"
        + (f'<ul class="flags">{reasons}</ul>' if reasons else "")
        + "</div>"
    )


def qa_reference_note(ctx: LotContext) -> str:
    """Which reference the lot's units were judged against (its own lot or the fleet
    history of earlier lots), the threshold and the limits in force."""
    qa = ctx.qa_lot or {}
    parts = []
    if qa:
        ref = {
            "lot": "the lot itself",
            "fleet history": "the fleet history",
            "none": "no reference (too few units, no fleet history)",
        }.get(qa.get("reference"), str(qa.get("reference")))
        parts.append(
            f"<b>Reference:</b> {esc(ref)}"
            + (f" ({esc(qa.get('reference_detail'))})" if qa.get("reference_detail") else "")
            + f"; |robust z| threshold {fmt(qa.get('z_threshold'), 2)}; judged "
            f"{esc(fmt_time(qa.get('judged_at')) or DASH)}."
        )
    else:
        parts.append("<b>Reference:</b> not recorded (the lot was not re-flagged by this version).")
    if ctx.limits:
        parts.append(
            f"<b>Limits:</b> {len(ctx.limits)} parameter(s) "
            + ", ".join(
                f"{esc(m)}.{esc(n)} ({esc(lim.written)})" for (m, n), lim in sorted(ctx.limits.items())
            )
            + "."
        )
    else:
        parts.append("<b>Limits:</b> none configured.")
    if ctx.limits_problem:
        parts.append(esc(ctx.limits_problem))
    return f'<p class="note qa-reference">{" ".join(parts)}</p>'


def protocol_notes_note(ctx: LotContext, unit: str | None = None) -> str:
    """What the lot's protocol cannot observe (schemas.protocol_notes), once for the lot or
    the unit, with the sessions it concerns ("" when the protocol has no such note)."""
    sessions = ctx.sessions if unit is None or ctx.sessions is None else ctx.unit_rows("sessions", unit)
    notes = lot_notes(sessions)
    if not notes:
        return ""
    return "".join(f'<p class="note protocol-note"><b>Protocol:</b> {esc(n.line())}</p>' for n in notes)


def build(ctx: LotContext, page: Page, unit: str | None) -> str:
    """The lot's summary: run facts and session counts, what its protocol cannot observe,
    the reference its units were judged against, the flags."""
    return (
        f"{kpi_block(ctx)}{protocol_notes_note(ctx)}<h3>Flags: limit failures and outliers</h3>"
        f"{qa_reference_note(ctx)}{flags_list(ctx)}"
    )


def build_unit_flags(ctx: LotContext, page: Page, unit: str) -> str | None:
    """A unit's flags (None when it has none)."""
    n_flags = ctx.n_param_flags(unit) + (unit in ctx.unit_level_flags)
    return flags_list(ctx, unit, link=False) if n_flags else None
