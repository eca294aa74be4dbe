"""Sessions: failed and warned sessions, units not freshly calibrated."""

from __future__ import annotations

from reports.context import (
    LotContext,
    as_text,
)
from reports.html import (
    Page,
    esc,
    missing,
    table,
)


def sessions_section(ctx: LotContext, link_units: bool = True) -> str:
    s = ctx.sessions
    if s is None:
        return missing("Sessions", "sessions.parquet is absent")
    out = []
    failed = s[s["status"] == "failed"].sort_values(["unit", "rep"])
    if len(failed):
        rows = []
        for r in failed.itertuples():
            u = f'<a href="#unit-{esc(r.unit)}">{esc(r.unit)}</a>' if link_units else esc(r.unit)
            rows.append(
                (
                    {"data-unit": r.unit},
                    [
                        u,
                        str(r.rep),
                        f'<span class="mono">{esc(as_text(r.error_code))}</span>',
                        esc(as_text(r.message)),
                        f'<span class="mono">{esc(getattr(r, "path", ""))}</span>',
                    ],
                )
            )
        out.append(
            f"<h3>Failed sessions ({len(failed)})</h3>"
            + table(
                ["Unit", "Rep", "Error code", "Reason", "Session"], rows, cls="failed-sessions", text_cols=5
            )
        )
    else:
        out.append('<p class="note">No failed session.</p>')
    warned = s[s["status"] == "warned"].sort_values(["unit", "rep"])
    if len(warned):
        rows = [
            [esc(r.unit), str(r.rep), esc(as_text(getattr(r, "warnings", "")))] for r in warned.itertuples()
        ]
        out.append(
            f"<h3>Sessions with warnings ({len(warned)})</h3>"
            + table(["Unit", "Rep", "Warnings"], rows, cls="wrap", text_cols=3)
        )
    u = ctx.units_table
    if u is not None and len(u) and "state" in u:
        stale = u[u["state"].astype(str) != "calibrated"]
        if len(stale):
            rows = [[esc(r.unit), esc(r.state), esc(getattr(r, "reason", ""))] for r in stale.itertuples()]
            out.append(
                f"<h3>Units not freshly calibrated ({len(stale)})</h3>"
                + table(["Unit", "State", "Why"], rows, cls="wrap", text_cols=3)
            )
    return "".join(out)


def build(ctx: LotContext, page: Page, unit: str | None) -> str:
    """The lot's failed and warned sessions and the units not freshly calibrated."""
    return sessions_section(ctx)


def build_unit_failed(ctx: LotContext, page: Page, unit: str) -> str | None:
    """A unit's failed sessions with their error codes (None when none failed)."""
    if not ctx.session_counts(unit).get("failed") or ctx.sessions is None:
        return None
    f = ctx.unit_rows("sessions", unit)
    f = f[f["status"] == "failed"]
    return (
        '<ul class="flags">'
        + "".join(
            f'<li>rep {r.rep}: <span class="mono">{esc(r.error_code)}</span> {esc(r.message)}</li>'
            for r in f.itertuples()
        )
        + "</ul>"
    )
