"""Model discovery: the findings by kind and each finding's evidence figures."""

from __future__ import annotations

import math

import numpy as np
import pandas as pd

from reports.context import (
    LotContext,
)
from reports.html import (
    Page,
    arr,
    esc,
    missing,
    table,
)
from reports.sections.common import legend_top

_DISC_KIND_ORDER = {"named": 0, "confounded": 1, "unexplained": 2, "partial": 3, "negligible": 4}


_DISC_KIND_TEXT = {
    "named": "Named effects (applied)",
    "confounded": "Confounded: the steps cannot tell these apart (combined fit applied, none named)",
    "unexplained": "Unexplained misfit (no catalogue effect accounts for it)",
    "partial": "Partial candidates (significant, leave their channels misfit; not applied)",
}


def _disc_rows(df: pd.DataFrame | None) -> pd.DataFrame:
    if df is None or not len(df) or "kind" not in df.columns:
        return pd.DataFrame()
    d = df[df["kind"].isin(list(_DISC_KIND_ORDER))].copy()
    d["_order"] = d["kind"].map(_DISC_KIND_ORDER)
    return d.sort_values(["_order", "unit", "effect"])


def _cell(v, sig: int | None = None) -> str:
    if v is None or (isinstance(v, float) and math.isnan(v)):
        return ""
    if sig is not None and isinstance(v, (float, np.floating, int, np.integer)):
        return f"{float(v):.{sig}g}"
    return esc(str(v))


def _lines(v, sep: str = "; ") -> str:
    """A text cell with one item per line: a confounded set's readings (`` | ``), and the
    items ``sep`` separates (kept at the end of the line: parameters, alternatives)."""
    text = _cell(v).replace(" | ", "<br>")
    return text.replace(esc(sep), esc(sep.rstrip()) + "<br>")


def _kind_table(rows: pd.DataFrame, kind: str, with_unit_col: bool) -> str:
    headers = (["Unit"] if with_unit_col else []) + [
        "Effects" if kind == "confounded" else "Effect",
        "Channels",
        "Estimate ± standard error",
        "Evidence",
        "Held-out rms before",
        "after (σ)",
        "gain",
    ]
    if kind == "confounded":
        headers.append("Steps that would separate them")
    body = []
    for r in rows.itertuples():
        cells = [f'<a href="#unit-{esc(r.unit)}">{esc(r.unit)}</a>'] if with_unit_col else []
        effect = str(r.effect).removeprefix("confounded: ") if kind == "confounded" else r.effect
        cells += [
            _lines(effect, ", "),
            _cell(r.channels),
            _lines(r.estimates),
            _cell(r.evidence),
            _cell(r.heldout_rms_before, 3),
            _cell(r.heldout_rms_after, 3),
            _cell(r.gain, 3),
        ]
        if kind == "confounded":
            # the step sets (the row's effects say what they separate)
            text = str(r.separated_by or "")
            cells.append(_lines(text.split("; add ", 1)[1] if "; add " in text else text, " or "))
        body.append(cells)
    return table(
        headers,
        body,
        cls=f"discovery {kind}",
        text_cols=len(headers) - 3 if kind != "confounded" else len(headers),
    )


def discovery_tables(df: pd.DataFrame | None, with_unit_col: bool) -> str:
    """Findings by kind (named, confounded, unexplained, partial), then the negligible
    terms in a folded list. Text cells only: no JSON."""
    d = _disc_rows(df)
    if not len(d):
        return ""
    out = []
    for kind, title in _DISC_KIND_TEXT.items():
        rows = d[d["kind"] == kind]
        if len(rows):
            out.append(f"<h4>{esc(title)}</h4>" + _kind_table(rows, kind, with_unit_col))
    neg = d[d["kind"] == "negligible"]
    if len(neg):
        items = "".join(
            f"<li>{(esc(r.unit) + ': ') if with_unit_col else ''}{esc(r.effect)} "
            f"({esc(r.estimates)}; held-out gain {_cell(r.gain, 3)})</li>"
            for r in neg.itertuples()
        )
        out.append(
            f'<details class="negligible"><summary>Negligible terms ({len(neg)}): '
            f"significant, but the unit fits without them or their held-out gain is "
            f"too small; not applied</summary><ul>{items}</ul></details>"
        )
    advice = sorted({a for a in d.get("advice", pd.Series(dtype=object)).dropna() if a})
    if advice:
        out.append(
            '<h4>Protocol advisor</h4><ul class="advice">'
            + "".join(f"<li>{esc(line)}</li>" for a in advice for line in a.split(" | "))
            + "</ul>"
        )
    return "".join(out)


def discovery_table(df: pd.DataFrame, with_unit_col: bool) -> str:
    return discovery_tables(df, with_unit_col)


def unit_discovery_table(ctx: LotContext, unit: str) -> str:
    """The findings of one unit ("" when it has none)."""
    d = ctx.discovery
    if d is None or not len(d):
        return ""
    return discovery_tables(d[d["unit"] == unit], with_unit_col=False)


def evidence_figures(ctx: LotContext, page: Page, unit: str) -> str:
    """For each named, confounded or unexplained finding of the unit, per channel: the
    baseline residual against the variable that drives it (every repetition), the fitted
    effect over it, and the residual after."""
    ev = ctx.evidence
    if ev is None or not len(ev):
        return ""
    u = ev[ev["unit"] == unit]
    out = []
    for (effect, channel), g in u.groupby(["effect", "channel"], sort=False):
        x = g["x"].to_numpy(float)
        order = np.argsort(x, kind="stable")
        first = g.iloc[0]
        xt = f"{first['x_label']}" + (f" ({first['x_unit']})" if first["x_unit"] else "")
        data = [
            {
                "type": "scatter",
                "mode": "markers",
                "x": arr(x),
                "y": arr(g["before"].to_numpy(float)),
                "name": "residual, affine model",
                "marker": {"color": "#f58518", "size": 5, "opacity": 0.7},
            },
            {
                "type": "scatter",
                "mode": "markers",
                "x": arr(x),
                "y": arr(g["after"].to_numpy(float)),
                "name": "residual after",
                "marker": {"color": "#4c78a8", "size": 5, "opacity": 0.7},
            },
        ]
        fitted = g["fitted"].to_numpy(float)
        if np.isfinite(fitted).any():
            data.insert(
                1,
                {
                    "type": "scatter",
                    "mode": "lines",
                    "x": arr(x[order]),
                    "y": arr(fitted[order]),
                    "name": "fitted effect",
                    "line": {"color": "#222", "width": 2},
                },
            )
        layout = {
            "legend": legend_top(),
            "margin": {"t": 40, "b": 50, "l": 70, "r": 15},
            "xaxis": {"title": {"text": xt}},
            "yaxis": {"title": {"text": f"{channel} residual ({first['y_unit']})"}},
        }
        out.append(
            f"<h5>{esc(effect)} · {esc(channel)}</h5>"
            + page.figure(
                {"data": data, "layout": layout}, height=300, name=f"{unit} {effect} {channel} evidence"
            )
        )
    if not out:
        return ""
    return '<div class="evidence">' + "".join(out) + "</div>"


def build(ctx: LotContext, page: Page, unit: str | None) -> str:
    """The lot's discovery findings, one table per kind, with a unit column."""
    if ctx.discovery is None:
        return missing("Model discovery", "discovery.parquet is absent (discovery not run)")
    if not len(ctx.discovery):
        return '<p class="note">Model discovery ran and found no effect.</p>'
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
    return f'<p class="note">{esc(" ".join(notes))}</p>' + discovery_table(d, with_unit_col=True)


def build_unit(ctx: LotContext, page: Page, unit: str) -> str | None:
    """A unit's findings and the evidence figures of each (None when it has none)."""
    if ctx.discovery is None:
        return None
    dt = unit_discovery_table(ctx, unit)
    return dt + evidence_figures(ctx, page, unit) if dt else None
