"""Fleet index: links to every lot report (and unit report), the lots' current state, the
run log, and the trend of each key parameter's lot median and spread over the runs.

``write_fleet_index(results_root)`` writes ``results_root/reports/index.html``.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pandas as pd

from calib_core.figure_statistics import lot_trends
from reports.history import GROUP_TITLES, KEY_ELEMENTS, history_frame
from reports.html import DASH, Page, arr, esc, fmt_time, grid, kpi, missing, table, write_atomic
from reports.lot import lot_report_path
from reports.store import StoreView

LOT_COLOURS = [
    "#4c78a8",
    "#f58518",
    "#54a24b",
    "#e45756",
    "#72b7b2",
    "#b279a2",
    "#eeca3b",
    "#9d755d",
    "#ff9da6",
    "#bab0ac",
]


def trend_figure(tr: pd.DataFrame, group: str) -> dict:
    elems = [e for e in KEY_ELEMENTS if e[0] == group]
    ncols = 3
    nrows = len(elems) // ncols
    layout, refs = grid(nrows, ncols, [e[1] for e in elems], hspace=0.07, vspace=0.32 / nrows)
    lots = list(dict.fromkeys(tr["lot"].astype(str)))
    # each lot's rows, times and hover texts once (not once per element: 24 elements x lots
    # of boolean filters cost ~0.3 s per fleet index)
    by_lot = {}
    for lot in lots:
        d = tr[tr["lot"] == lot]
        cols = {c: d[c].to_numpy(float) for e in elems for c in (e[1], e[1] + "_spread")}
        by_lot[lot] = (
            cols,
            [t.isoformat() for t in d["time"]],
            [
                f"{lot} · acquired {t:%Y-%m-%d %H:%M} UTC ({src}) · {u} units"
                for t, src, u in zip(d["time"], d["time_source"], d["n_units"])
            ],
        )
    data = []
    for k, e in enumerate(elems):
        xr, yr = refs[k]
        n = e[1]
        for li, lot in enumerate(lots):
            cols, times, texts = by_lot[lot]
            spread = cols[n + "_spread"]
            c = LOT_COLOURS[li % len(LOT_COLOURS)]
            data.append(
                {
                    "type": "scatter",
                    "x": list(times),
                    "y": arr(cols[n]),
                    "mode": "lines+markers",
                    "name": lot,
                    "marker": {"color": c, "size": 6},
                    "line": {"color": c, "width": 1.5},
                    "error_y": {
                        "type": "data",
                        "array": arr(np.where(np.isnan(spread), 0.0, spread)),
                        "color": c,
                        "thickness": 1,
                        "width": 3,
                    },
                    "legendgroup": lot,
                    "showlegend": k == 0,
                    "xaxis": xr,
                    "yaxis": yr,
                    "text": list(texts),
                    "hovertemplate": (
                        f"{n}: median %{{y:.6g}} ± %{{error_y.array:.2g}}<br>%{{text}}<extra></extra>"
                    ),
                }
            )
        layout["xaxis" + xr[1:]].update(type="date", nticks=4)
    layout.update(
        legend={"orientation": "h", "y": 1.0 + 0.3 / nrows, "x": 1, "xanchor": "right", "yanchor": "bottom"},
        margin={"t": 60, "b": 35, "l": 70, "r": 15},
    )
    return {"data": data, "layout": layout}


def _lot_row(sessions: pd.DataFrame | None, summary: pd.DataFrame | None) -> dict:
    """What the index's lots table shows of one lot, from its rows of the sessions and
    summary tables (None: the table was never written): session counts by status, number of
    units, flagged units, last calibration time."""
    c = sessions["status"].astype(str).value_counts() if sessions is not None else pd.Series(dtype=int)
    flagged: list[str] = []
    units = set()
    if summary is not None:
        units |= set(summary["unit"].astype(str))
        if "flagged" in summary:
            flagged = sorted(
                set(summary.loc[summary["flagged"].fillna(False).astype(bool), "unit"].astype(str))
            )
    if sessions is not None:
        units |= set(sessions["unit"].astype(str))
    last = (
        sessions["calibrated_at"].dropna().astype(str).max()
        if sessions is not None and "calibrated_at" in sessions and len(sessions)
        else None
    )
    return {
        "sessions": {k: int(c.get(k, 0)) for k in ("ok", "warned", "failed")},
        "n_units": len(units),
        "flagged": flagged,
        "last": None if last is None or (isinstance(last, float) and np.isnan(last)) else str(last),
    }


# The lots table's rows, kept in cache/fleet_index.json: a lot's row is valid while its
# sessions and summary files are the same files (size, mtime, inode; every write replaces a
# file), so the index reads only the lots written since (a rerun: its own lot) instead of both
# tables whole. A missing, broken or foreign cache is rebuilt; a format-1.0 store (one flat
# file per table) is read whole, without cache.
FLEET_INDEX_CACHE_VERSION = 1
_LOT_ROW_TABLES = ("sessions", "summary")


def fleet_index_cache_path(view: StoreView) -> Path:
    return view.root / "cache" / "fleet_index.json"


def lot_rows(view: StoreView, lots: list[str]) -> dict[str, dict]:
    """:func:`_lot_row` of each lot, from the cache where its files are unchanged."""
    stats = {
        name: view.store.partition_stats(name) if view.store.has_table(name) else {}
        for name in _LOT_ROW_TABLES
    }
    if any(st is None for st in stats.values()):  # format 1.0: the whole tables, as read
        tables = {name: view.table(name) for name in _LOT_ROW_TABLES}
        return {
            lot: _lot_row(*(None if t is None else t[t["lot"] == lot] for t in tables.values()))
            for lot in lots
        }
    try:
        doc = json.loads(fleet_index_cache_path(view).read_text())
        cached = doc["lots"] if doc.get("version") == FLEET_INDEX_CACHE_VERSION else {}
    except (OSError, ValueError, KeyError, TypeError, AttributeError):
        cached = {}
    out, entries = {}, {}
    for lot in lots:
        files = {name: list(st[lot]) if lot in st else None for name, st in stats.items()}
        entry = cached.get(lot) if isinstance(cached, dict) else None
        if isinstance(entry, dict) and entry.get("files") == files:
            row = entry["row"]
        else:
            row = _lot_row(*(view.of(name, lot=lot) for name in _LOT_ROW_TABLES))
        out[lot] = row
        entries[lot] = {"files": files, "row": row}
    if entries != cached:
        try:  # a cache: a store we may not write to only costs the reading
            write_atomic(
                fleet_index_cache_path(view),
                json.dumps({"version": FLEET_INDEX_CACHE_VERSION, "lots": entries}),
            )
        except OSError:
            pass
    return out


def render_fleet_index(results_root: str | Path, view: StoreView | None = None) -> str:
    """``view``: a StoreView of ``results_root`` to share its cached reads with other reports
    written in the same pass."""
    view = view if view is not None else StoreView(results_root)
    page = Page("mimucal fleet index")
    lots = view.lots()
    body = []

    # lots table
    rows = []
    tot = {"ok": 0, "warned": 0, "failed": 0}
    flagged_total = 0
    for lot, r in lot_rows(view, lots).items():
        for k in tot:
            tot[k] += r["sessions"][k]
        flagged_total += len(r["flagged"])
        path = lot_report_path(view.root, lot)
        link = (
            f'<a href="{esc(path.name)}">{esc(lot)}</a>'
            if path.exists()
            else f'{esc(lot)} <span class="note">(report not written)</span>'
        )
        flag_html = (
            " ".join(
                f'<a href="{esc(path.name)}#unit-{esc(u)}"><span class="badge flag">⚑ {esc(u)}</span></a>'
                for u in r["flagged"]
            )
            or "none"
        )
        rows.append(
            (
                {"data-lot": lot},
                [
                    link,
                    str(r["n_units"]),
                    str(r["sessions"]["ok"]),
                    str(r["sessions"]["warned"]),
                    str(r["sessions"]["failed"]),
                    flag_html,
                    esc(fmt_time(r["last"]) or DASH),
                ],
            )
        )
    kpis = [
        kpi("Lots", str(len(lots))),
        kpi("Sessions ok", str(tot["ok"]), "good"),
        kpi("Warned", str(tot["warned"]), "warn" if tot["warned"] else ""),
        kpi("Failed", str(tot["failed"]), "bad" if tot["failed"] else ""),
        kpi("Units flagged", str(flagged_total), "bad" if flagged_total else "good"),
    ]
    lots_html = (
        table(
            ["Lot report", "Units", "Sessions ok", "Warned", "Failed", "Flagged units", "Last calibrated"],
            rows,
            cls="sortable lots",
            text_cols=1,
            attrs=' id="lots"',
        )
        if lots
        else missing("Lots", "the results store holds no lot yet")
    )
    body.append(
        f'<section id="summary"><h2>Lots</h2><div class="kpis">{"".join(kpis)}</div>'
        f"<h3>Lot reports</h3>{lots_html}</section>"
    )

    # unit reports present
    udir = view.reports_dir / "units"
    unit_files = sorted(udir.glob("*.html")) if udir.is_dir() else []
    if unit_files:
        links = " ".join(f'<a href="units/{esc(p.name)}">{esc(p.stem)}</a>' for p in unit_files)
        body.append(
            f'<section id="unit-reports"><h2>Unit reports ({len(unit_files)})</h2><p>{links}</p></section>'
        )

    # trends
    h = history_frame(view)
    tr = lot_trends(h, [e[1] for e in KEY_ELEMENTS])
    if len(tr):
        figs = "".join(
            f"<h3>{GROUP_TITLES[g]}</h3>"
            + page.figure(
                trend_figure(tr, g), height=200 + 190 * (3 if g.startswith("K") else 1), name=f"trend {g}"
            )
            for g in ("K_g", "w0", "K_a", "f0")
        )
        src = ", ".join(sorted(set(", ".join(tr["time_source"]).split(", "))))
        trend_html = (
            '<p class="note">Per lot: median over all the lot\'s units of each key parameter '
            "(points; each unit's current calibration) and its spread (error bars: "
            "the lot scatter, 1.4826 × MAD across units, from 3 units), at the time the lot "
            "was acquired (median of its "
            f"units' acquisition times; from: {esc(src)}).</p>" + figs
        )
    else:
        trend_html = missing("Parameter trends", "no calibration files under calibrations/")
    body.append(f'<section id="trends"><h2>Trends by acquisition date</h2>{trend_html}</section>')

    # run log
    runs = view.runs
    if runs:
        rrows = []
        for r in reversed(runs[-50:]):
            lots_r = r.get("lots")
            rrows.append(
                [
                    f'<span class="mono">{esc(r.get("run_id"))}</span>',
                    esc(fmt_time(r["_time"]) or DASH),
                    esc(r.get("kind") or r.get("flow") or DASH),
                    esc(r.get("code_version") or DASH),
                    esc(", ".join(map(str, lots_r)) if isinstance(lots_r, list) else (lots_r or DASH)),
                ]
            )
        runs_html = table(["Run id", "Time", "Kind", "Code version", "Lots"], rrows, text_cols=5)
    else:
        runs_html = missing("Run log", "no runs/*.json")
    body.append(f'<section id="runs"><h2>Runs</h2>{runs_html}</section>')

    header = (
        '<header class="report"><h1>mimucal · fleet calibration index</h1>'
        f'<div class="sub">{len(lots)} lots · results store '
        f'<span class="mono">{esc(view.root)}</span></div></header>'
    )
    return page.render(header, "".join(body))


def write_fleet_index(results_root: str | Path, view: StoreView | None = None) -> Path:
    """Write ``results_root/reports/index.html`` and return its path."""
    text = render_fleet_index(results_root, view)
    path = Path(results_root) / "reports" / "index.html"
    write_atomic(path, text)
    return path
