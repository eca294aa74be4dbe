"""Fleet index: links to every lot report (and unit report), the lots' current state, the
run log, and the trend of each key parameter's lot median and spread over the runs.

``write_fleet_index(results_root)`` writes ``results_root/reports/index.html``.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd

from reports.history import GROUP_TITLES, KEY_ELEMENTS, history_frame
from reports.html import DASH, Page, arr, esc, fmt_time, grid, kpi, missing, table, write_atomic
from reports.lot import lot_report_path
from reports.store import StoreView

LOT_COLOURS = ["#4c78a8", "#f58518", "#54a24b", "#e45756", "#72b7b2", "#b279a2", "#eeca3b",
               "#9d755d", "#ff9da6", "#bab0ac"]


def lot_trends(h: pd.DataFrame) -> pd.DataFrame:
    """Per lot and run: median over units of each key element and its spread (1.4826 MAD,
    a robust standard deviation). Calibrations without a run id are grouped by UTC day."""
    if not len(h):
        return pd.DataFrame()
    h = h.copy()
    h["run"] = h["run_id"].where(h["run_id"].notna(), h["time"].map(lambda t: t.strftime("%Y-%m-%d")))
    names = [e[1] for e in KEY_ELEMENTS]
    rows = []
    for (lot, run), g in h.groupby(["lot", "run"], sort=False, dropna=False):
        row = {"lot": lot, "run": run, "time": g["time"].max(), "n_units": g["unit"].nunique()}
        for n in names:
            v = g[n].to_numpy(float)
            v = v[np.isfinite(v)]
            med = float(np.median(v)) if len(v) else np.nan
            row[n] = med
            row[n + "_spread"] = float(1.4826 * np.median(np.abs(v - med))) if len(v) > 1 else np.nan
        rows.append(row)
    return pd.DataFrame(rows).sort_values("time")


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
        by_lot[lot] = (cols, [t.isoformat() for t in d["time"]],
                       [f"{lot} · run {r} · {u} units" for r, u in zip(d["run"], d["n_units"])])
    data = []
    for k, e in enumerate(elems):
        xr, yr = refs[k]
        n = e[1]
        for li, lot in enumerate(lots):
            cols, times, texts = by_lot[lot]
            spread = cols[n + "_spread"]
            c = LOT_COLOURS[li % len(LOT_COLOURS)]
            data.append({"type": "scatter", "x": list(times),
                         "y": arr(cols[n]), "mode": "lines+markers", "name": lot,
                         "marker": {"color": c, "size": 6}, "line": {"color": c, "width": 1.5},
                         "error_y": {"type": "data", "array": arr(np.where(np.isnan(spread), 0.0, spread)),
                                     "color": c, "thickness": 1, "width": 3},
                         "legendgroup": lot, "showlegend": k == 0, "xaxis": xr, "yaxis": yr,
                         "text": list(texts),
                         "hovertemplate": f"{n}: median %{{y:.6g}} ± %{{error_y.array:.2g}}<br>%{{text}}<extra></extra>"})
        layout["xaxis" + xr[1:]].update(type="date", nticks=4)
    layout.update(legend={"orientation": "h", "y": 1.0 + 0.3 / nrows, "x": 1, "xanchor": "right",
                          "yanchor": "bottom"}, margin={"t": 60, "b": 35, "l": 70, "r": 15})
    return {"data": data, "layout": layout}


def render_fleet_index(results_root: str | Path, view: StoreView | None = None) -> str:
    """``view``: a StoreView of ``results_root`` to share its cached reads with other reports
    written in the same pass."""
    view = view if view is not None else StoreView(results_root)
    page = Page("mimucal fleet index")
    lots = view.lots()
    sessions, summary = view.table("sessions"), view.table("summary")
    body = []

    # lots table
    rows = []
    tot = {"ok": 0, "warned": 0, "failed": 0}
    flagged_total = 0
    for lot in lots:
        s = sessions[sessions["lot"] == lot] if sessions is not None else None
        c = s["status"].astype(str).value_counts() if s is not None else pd.Series(dtype=int)
        for k in tot:
            tot[k] += int(c.get(k, 0))
        flagged: list[str] = []
        units = set()
        if summary is not None:
            sl = summary[summary["lot"] == lot]
            units |= set(sl["unit"].astype(str))
            if "flagged" in sl:
                flagged = sorted(set(sl.loc[sl["flagged"].fillna(False).astype(bool), "unit"].astype(str)))
        if s is not None:
            units |= set(s["unit"].astype(str))
        flagged_total += len(flagged)
        last = s["calibrated_at"].dropna().astype(str).max() if s is not None and "calibrated_at" in s and len(s) else None
        path = lot_report_path(view.root, lot)
        link = (f'<a href="{esc(path.name)}">{esc(lot)}</a>' if path.exists()
                else f'{esc(lot)} <span class="note">(report not written)</span>')
        flag_html = (" ".join(f'<a href="{esc(path.name)}#unit-{esc(u)}"><span class="badge flag">⚑ {esc(u)}</span></a>'
                              for u in flagged) or "none")
        rows.append(({"data-lot": lot}, [link, str(len(units)), str(int(c.get("ok", 0))), str(int(c.get("warned", 0))),
                                         str(int(c.get("failed", 0))), flag_html, esc(fmt_time(last) or DASH)]))
    kpis = [kpi("Lots", str(len(lots))), kpi("Sessions ok", str(tot["ok"]), "good"),
            kpi("Warned", str(tot["warned"]), "warn" if tot["warned"] else ""),
            kpi("Failed", str(tot["failed"]), "bad" if tot["failed"] else ""),
            kpi("Units flagged", str(flagged_total), "bad" if flagged_total else "good")]
    lots_html = (table(["Lot report", "Units", "Sessions ok", "Warned", "Failed", "Flagged units", "Last calibrated"],
                       rows, cls="sortable lots", text_cols=1, attrs=' id="lots"')
                 if lots else missing("Lots", "the results store holds no lot yet"))
    body.append(f'<section id="summary"><h2>Lots</h2><div class="kpis">{"".join(kpis)}</div>'
                f"<h3>Lot reports</h3>{lots_html}</section>")

    # unit reports present
    udir = view.reports_dir / "units"
    unit_files = sorted(udir.glob("*.html")) if udir.is_dir() else []
    if unit_files:
        links = " ".join(f'<a href="units/{esc(p.name)}">{esc(p.stem)}</a>' for p in unit_files)
        body.append(f'<section id="unit-reports"><h2>Unit reports ({len(unit_files)})</h2><p>{links}</p></section>')

    # trends
    h = history_frame(view)
    tr = lot_trends(h)
    if len(tr):
        figs = "".join(f"<h3>{GROUP_TITLES[g]}</h3>" + page.figure(trend_figure(tr, g),
                                                                   height=200 + 190 * (3 if g.startswith("K") else 1),
                                                                   name=f"trend {g}")
                       for g in ("K_g", "w0", "K_a", "f0"))
        trend_html = ('<p class="note">Per lot and run: median over the lot\'s units of each key parameter '
                      '(points) and its spread (error bars: 1.4826 × MAD across units), from every '
                      'calibration file kept under calibrations/.</p>' + figs)
    else:
        trend_html = missing("Parameter trends", "no calibration files under calibrations/")
    body.append(f'<section id="trends"><h2>Trends over runs</h2>{trend_html}</section>')

    # run log
    runs = view.runs
    if runs:
        rrows = []
        for r in reversed(runs[-50:]):
            lots_r = r.get("lots")
            rrows.append([f'<span class="mono">{esc(r.get("run_id"))}</span>', esc(fmt_time(r["_time"]) or DASH),
                          esc(r.get("kind") or r.get("flow") or DASH), esc(r.get("code_version") or DASH),
                          esc(", ".join(map(str, lots_r)) if isinstance(lots_r, list) else (lots_r or DASH))])
        runs_html = table(["Run id", "Time", "Kind", "Code version", "Lots"], rrows, text_cols=5)
    else:
        runs_html = missing("Run log", "no runs/*.json")
    body.append(f'<section id="runs"><h2>Runs</h2>{runs_html}</section>')

    header = ('<header class="report"><h1>mimucal · fleet calibration index</h1>'
              f'<div class="sub">{len(lots)} lots · results store <span class="mono">{esc(view.root)}</span></div></header>')
    return page.render(header, "".join(body))


def write_fleet_index(results_root: str | Path, view: StoreView | None = None) -> Path:
    """Write ``results_root/reports/index.html`` and return its path."""
    text = render_fleet_index(results_root, view)
    path = Path(results_root) / "reports" / "index.html"
    write_atomic(path, text)
    return path
