"""Page and figure assembly shared by the lot, unit and fleet reports.

One self-contained HTML file per report: plotly.js is inlined once in ``<head>``; each
figure is a ``<div class="figure">`` followed by its JSON spec in a
``<script type="application/json">``, drawn by a small inline runtime. Figures inside a
closed ``<details>`` are drawn when it is opened (a 50-unit lot has ~100 per-unit figures:
drawing them all at load would cost seconds and plotly cannot size a hidden div). The
plotly layout template is shared once per page instead of repeated in every figure
(plotly.py writes ~7 kB of template per figure). Nothing refers to a URL: the file works
from ``file://`` with no network.
"""

from __future__ import annotations

import base64
import functools
import html
import json
import math
from collections.abc import Iterable, Sequence
from datetime import UTC, datetime
from typing import Any

import numpy as np
import plotly.graph_objects as go
from plotly.offline import get_plotlyjs

from schemas.display import decimals_for, spread_unit, value_unit  # noqa: F401 (decimals_for: re-exported)

# Colours: the clean population and the flagged units must be told apart at a glance and in
# grey-scale print (flagged points are also larger, diamond-shaped and labelled).
CLEAN = "#4c78a8"
FLAGGED = "#d62728"
LIMIT = "#b45309"  # a failed acceptance limit: its own colour, symbol (x) and badge
CHANNEL_COLOURS = {"x": "#1f77b4", "y": "#2ca02c", "z": "#9467bd"}
CASE_COLOURS = {"none": "#d62728", "static": "#ff7f0e", "static+dynamic": "#2ca02c"}

MINUS = "\u2212"
DASH = "\u2013"

_TEMPLATE = {
    "layout": {
        "font": {
            "family": "system-ui, -apple-system, 'Segoe UI', 'DejaVu Sans', sans-serif",
            "size": 12,
            "color": "#1f2933",
        },
        "paper_bgcolor": "#ffffff",
        "plot_bgcolor": "#f8fafc",
        "colorway": [
            "#4c78a8",
            "#f58518",
            "#54a24b",
            "#b279a2",
            "#e45756",
            "#72b7b2",
            "#eeca3b",
            "#9d755d",
            "#bab0ac",
            "#ff9da6",
        ],
        "xaxis": {
            "gridcolor": "#e2e8f0",
            "zerolinecolor": "#94a3b8",
            "linecolor": "#cbd5e1",
            "automargin": True,
        },
        "yaxis": {
            "gridcolor": "#e2e8f0",
            "zerolinecolor": "#94a3b8",
            "linecolor": "#cbd5e1",
            "automargin": True,
        },
        "hoverlabel": {"font": {"size": 12}},
        "margin": {"l": 60, "r": 20, "t": 40, "b": 45},
        "legend": {"orientation": "h", "y": -0.18},
    }
}

_CSS = """
:root { --fg:#1f2933; --muted:#52606d; --line:#d9e2ec; --bg:#f5f7fa; --flag:#d62728;
        --flagbg:#fde8e8; --ok:#2f855a; --warn:#b7791f; --accent:#2b6cb0; }
* { box-sizing: border-box; }
body { margin:0; font: 14px/1.45 system-ui, -apple-system, "Segoe UI", "DejaVu Sans", sans-serif;
       color:var(--fg); background:var(--bg); }
header.report { background:#1f2d3d; color:#fff; padding:18px 28px 14px; }
header.report h1 { margin:0 0 4px; font-size:22px; font-weight:600; }
header.report .sub { color:#cbd2d9; font-size:13px; }
header.report a { color:#bee3f8; }
main { max-width:1320px; margin:0 auto; padding:18px 28px 40px; }
section { background:#fff; border:1px solid var(--line); border-radius:6px; padding:14px 18px;
          margin:0 0 18px; }
h2 { font-size:17px; margin:0 0 10px; }
h3 { font-size:15px; margin:16px 0 6px; }
h4 { font-size:13px; margin:12px 0 4px; color:var(--muted); }
p.note, .note { color:var(--muted); font-size:12.5px; margin:4px 0 8px; }
p.missing { color:var(--warn); background:#fffbea; border-left:3px solid #f0b429;
            padding:6px 10px; margin:6px 0; }
.kpis { display:flex; flex-wrap:wrap; gap:10px; margin:0; }
.kpi { border:1px solid var(--line); border-radius:6px; padding:8px 12px; min-width:96px;
       background:#fff; }
.kpi .k { font-size:11.5px; color:var(--muted); text-transform:uppercase; letter-spacing:.03em; }
.kpi .v { font-size:18px; font-weight:600; }
.kpi .v small { font-size:12px; font-weight:400; color:var(--muted); }
.kpi.bad .v { color:var(--flag); } .kpi.good .v { color:var(--ok); } .kpi.warn .v { color:var(--warn); }
.tablewrap { overflow:auto; max-height:640px; border:1px solid var(--line); border-radius:4px; }
table { border-collapse:collapse; font-size:12.5px; font-variant-numeric: tabular-nums; }
th, td { padding:3px 8px; border-bottom:1px solid #edf2f7; text-align:right; white-space:nowrap; }
th { background:#f0f4f8; font-weight:600; position:sticky; top:0; z-index:1; }
thead tr.group th { top:0; text-align:center; border-left:1px solid var(--line); }
thead tr.group + tr th { top:24px; }
td.text, th.text { text-align:left; }
table.failed-sessions td, table.wrap td { white-space:normal; min-width:60px; max-width:640px; }
table.sortable thead tr:last-child th { cursor:pointer; user-select:none; }
table.sortable th[aria-sort=ascending]::after { content:" \\25B2"; font-size:9px; }
table.sortable th[aria-sort=descending]::after { content:" \\25BC"; font-size:9px; }
table.params td:first-child, table.params th:first-child { position:sticky; left:0; background:#fff;
       z-index:2; text-align:left; }
table.params thead th:first-child { background:#f0f4f8; z-index:3; }
tr.flagged-unit td:first-child { color:var(--flag); font-weight:600; }
td.flagged { background:var(--flagbg); color:var(--flag); font-weight:600;
             outline:1px solid #f5b5b5; outline-offset:-1px; }
td.flagged::before { content:"\\2691\\00a0"; }
.badge { display:inline-block; padding:0 6px; border-radius:9px; font-size:11px; font-weight:600;
         vertical-align:1px; }
.badge.flag { background:var(--flag); color:#fff; }
.badge.limit { background:#b45309; color:#fff; }
.badge.unjudged { background:#d9e2ec; color:#1f2933; }
td.limit { background:#fdebd3; color:#b45309; font-weight:600; }
td.limit::before { content:"\\2716\\00a0"; }
.qa-reference { margin:4px 0 8px; }
.badge.failed { background:#742a2a; color:#fff; }
.badge.warned { background:#f0b429; color:#1f2933; }
.badge.ok { background:#c6f6d5; color:#22543d; }
table.paper { margin:4px 0 10px; }
table.paper td.avg { font-weight:600; background:#f7fafc; }
table.paper td.spread { color:var(--muted); }
table.paper tr.sep td { border-top:2px solid var(--line); }
details.unit { border:1px solid var(--line); border-radius:6px; margin:0 0 10px; background:#fff; }
details.unit > summary { padding:8px 14px; cursor:pointer; font-weight:600; }
details.unit > summary .meta { font-weight:400; color:var(--muted); margin-left:8px; }
details.unit[open] > summary { border-bottom:1px solid var(--line); }
details.unit > .body { padding:6px 16px 12px; }
.figure { width:100%; min-height:120px; }
.figure[data-state=failed] { background:var(--flagbg); }
.grid2 { display:flex; flex-wrap:wrap; gap:0 28px; align-items:flex-start; }
.grid2 > div { flex:0 1 auto; max-width:100%; overflow-x:auto; }
.toolbar { margin:0 0 10px; }
button { font:inherit; font-size:12.5px; padding:3px 10px; border:1px solid #9fb3c8; background:#fff;
         border-radius:4px; cursor:pointer; }
ul.flags { margin:4px 0 0; padding-left:20px; }
ul.flags li { margin:2px 0; }
.mono { font-family: "DejaVu Sans Mono", ui-monospace, monospace; font-size:12px; }
footer { color:var(--muted); font-size:12px; text-align:center; padding:10px; }
.tabs { display:flex; flex-wrap:wrap; gap:4px; margin:0 0 6px; border-bottom:2px solid var(--line); }
.tabs .tab { border:1px solid var(--line); border-bottom:none; border-radius:4px 4px 0 0;
             background:#f0f4f8; padding:4px 12px; margin-bottom:-2px; }
.tabs .tab[aria-selected=true] { background:#fff; border-color:var(--accent); border-bottom:2px solid #fff;
                                 font-weight:600; }
tr.lotstat td { background:#f7fafc; color:var(--muted); border-top:1px solid var(--line); }
table.params tr.lotstat td:first-child { background:#f7fafc; }
.print-only { display:none; }
@media print {
  body { background:#fff; font-size:11px; }
  main { max-width:none; padding:0 8px; }
  section { break-inside:auto; border:none; padding:4px 0; }
  .tabs, .toolbar, button { display:none; }
  .tabpanel[hidden] { display:block; }
  .print-only { display:block; }
  .tablewrap { overflow:visible; max-height:none; border:none; }
  th { position:static; }
  table.params td:first-child, table.params th:first-child { position:static; }
  .figure { break-inside:avoid; }
}
a { color:var(--accent); }
"""

_RUNTIME = """
(function () {
  "use strict";
  var TEMPLATE = %(template)s;
  var CONFIG = {displaylogo: false, responsive: true,
                modeBarButtonsToRemove: ["select2d", "lasso2d", "sendDataToCloud"],
                toImageButtonOptions: {format: "png", scale: 2}};
  var done = 0, failed = 0;
  function status() {
    document.body.setAttribute("data-figures-total", document.querySelectorAll(".figure").length);
    document.body.setAttribute("data-figures-rendered", done);
    document.body.setAttribute("data-figures-failed", failed);
  }
  function draw(el) {
    if (el.hasAttribute("data-state")) return;
    el.setAttribute("data-state", "drawing");
    var spec;
    try {
      spec = JSON.parse(document.getElementById(el.getAttribute("data-spec")).textContent);
    } catch (e) {
      el.setAttribute("data-state", "failed"); failed++; status();
      console.error("figure " + el.id + ": bad spec: " + e); return;
    }
    spec.layout = spec.layout || {};
    spec.layout.template = TEMPLATE;
    Plotly.newPlot(el, spec.data, spec.layout, CONFIG).then(function () {
      el.setAttribute("data-state", "rendered"); done++; status();
    }, function (e) {
      el.setAttribute("data-state", "failed"); failed++; status();
      console.error("figure " + el.id + ": " + e);
    });
  }
  function drawVisible() {
    var figs = document.querySelectorAll(".figure:not([data-state])");
    for (var i = 0; i < figs.length; i++) {
      var closed = figs[i].closest("details:not([open])");
      if (!closed) draw(figs[i]);
    }
  }
  function cellValue(row, idx) {
    var c = row.children[idx];
    if (!c) return "";
    var s = c.getAttribute("data-sort");
    return s === null ? c.textContent.trim() : s;
  }
  function makeSortable(table) {
    var heads = table.tHead.rows[table.tHead.rows.length - 1].cells;
    Array.prototype.forEach.call(heads, function (th, idx) {
      th.addEventListener("click", function () {
        var asc = th.getAttribute("aria-sort") !== "ascending";
        Array.prototype.forEach.call(heads, function (h) { h.removeAttribute("aria-sort"); });
        th.setAttribute("aria-sort", asc ? "ascending" : "descending");
        var body = table.tBodies[0];
        var all = Array.prototype.slice.call(body.rows);
        var fixed = all.filter(function (r) { return r.classList.contains("lotstat"); });
        var rows = all.filter(function (r) { return !r.classList.contains("lotstat"); });
        rows.sort(function (a, b) {
          var x = cellValue(a, idx), y = cellValue(b, idx);
          var nx = parseFloat(x), ny = parseFloat(y);
          var r = (!isNaN(nx) && !isNaN(ny)) ? nx - ny
                : (isNaN(nx) !== isNaN(ny)) ? (isNaN(nx) ? 1 : -1) : x.localeCompare(y);
          return asc ? r : -r;
        });
        rows.concat(fixed).forEach(function (r) { body.appendChild(r); });
      });
    });
  }
  function makeTabs(list) {
    var tabs = list.querySelectorAll("[role=tab]");
    Array.prototype.forEach.call(tabs, function (tab) {
      tab.addEventListener("click", function () {
        Array.prototype.forEach.call(tabs, function (t) {
          var on = t === tab;
          t.setAttribute("aria-selected", on ? "true" : "false");
          var panel = document.getElementById(t.getAttribute("data-tab"));
          if (panel) panel.hidden = !on;
        });
        drawVisible();
      });
    });
  }
  window.mimucalExpandAll = function (open) {
    var ds = document.querySelectorAll("details");
    for (var i = 0; i < ds.length; i++) ds[i].open = open;
    drawVisible();
  };
  document.addEventListener("toggle", function (e) {
    if (e.target.open) drawVisible();
  }, true);
  function start() {
    status();
    if (typeof Plotly === "undefined") { console.error("plotly.js missing"); return; }
    var tables = document.querySelectorAll("table.sortable");
    for (var i = 0; i < tables.length; i++) makeSortable(tables[i]);
    var lists = document.querySelectorAll("[role=tablist]");
    for (var j = 0; j < lists.length; j++) makeTabs(lists[j]);
    drawVisible();
  }
  if (document.readyState === "loading") document.addEventListener("DOMContentLoaded", start);
  else start();
})();
"""


def esc(x: Any) -> str:
    return html.escape("" if x is None else str(x), quote=True)


# ---------------------------------------------------------------------------- numbers/units


def display_unit(uom: str | None) -> tuple[str, float]:
    """(label shown, factor applied to values) for a stored unit of measure: the values'
    display of :mod:`schemas.display` (dimensionless ratios bare, biases in g as mg)."""
    shown = value_unit(uom)
    return shown.label, shown.factor


def spread_display(uom: str | None) -> tuple[str, float]:
    """(label shown, factor) for a spread of a quantity stored in ``uom``: ppm for
    dimensionless ratios, deg/h for gyro biases, mg for accelerometer biases
    (:mod:`schemas.display`)."""
    shown = spread_unit(uom)
    return shown.label, shown.factor


def fmt_spread(v: Any, factor: float, label: str, sig: int = 2) -> str:
    """A spread already in the stored unit, shown with ``factor`` and ``label``
    (:func:`spread_display`), e.g. "8.8 ppm"."""
    try:
        x = float(v) * factor
    except (TypeError, ValueError):
        return DASH
    if not math.isfinite(x):
        return DASH
    text = fmt(x, sig=sig) if abs(x) < 10**sig else fmt(x, decimals=0)
    return f"{text}\u00a0{esc(label)}" if label else text


def fmt(v: Any, decimals: int | None = None, sig: int = 5) -> str:
    try:
        x = float(v)
    except (TypeError, ValueError):
        return esc(v)
    if not math.isfinite(x):
        return DASH
    s = f"{x:.{decimals}f}" if decimals is not None else f"{x:.{sig}g}"
    if s.startswith("-"):
        s = MINUS + s[1:]
    return s


def td_numbers(
    values: Sequence[float], finite: Sequence[bool], decimals: int | None = None, sig: int = 5
) -> str:
    """``"".join(f"<td>{fmt(v, decimals, sig)}</td>")`` over a row of Python floats and
    their finiteness (from ``ndarray.tolist()``), the format specification built once."""
    if decimals is not None and all(finite):
        # fixed-point text holds no '-' but a leading sign: one replace for the whole row
        return ("<td>" + "</td><td>".join(map(f"{{:.{decimals}f}}".format, values)) + "</td>").replace(
            "-", MINUS
        )
    spec = f".{decimals}f" if decimals is not None else f".{sig}g"
    out = []
    for v, ok in zip(values, finite):
        if ok:
            t = format(v, spec)
            out.append("<td>" + (MINUS + t[1:] if t[0] == "-" else t) + "</td>")
        else:
            out.append("<td>" + DASH + "</td>")
    return "".join(out)


def with_unit(label: str) -> str:
    return f" [{label}]" if label else ""


def fmt_time(value: Any) -> str:
    """UTC time as 'YYYY-MM-DD HH:MM UTC' from an ISO string or datetime; '' if unknown."""
    if value is None or (isinstance(value, float) and math.isnan(value)):
        return ""
    try:
        t = (
            value
            if isinstance(value, datetime)
            else datetime.fromisoformat(str(value).replace("Z", "+00:00"))
        )
    except ValueError:
        return str(value)
    if t.tzinfo is None:
        t = t.replace(tzinfo=UTC)
    return t.astimezone(UTC).strftime("%Y-%m-%d %H:%M UTC")


# ---------------------------------------------------------------------------- HTML pieces


def table(
    headers: Sequence[str],
    rows: Iterable[Sequence[str]],
    cls: str = "",
    group_row: str = "",
    text_cols: int = 1,
    wrap: bool = True,
    attrs: str = "",
) -> str:
    """An HTML table; ``rows`` hold ready-made cell HTML (``<td>`` included when a string
    starts with '<td'), the first ``text_cols`` columns left-aligned."""
    head = "".join(
        f'<th class="text">{h}</th>' if i < text_cols else f"<th>{h}</th>" for i, h in enumerate(headers)
    )
    body = []
    for r in rows:
        if isinstance(r, str):  # a ready-made <tr>...</tr>
            body.append(r)
            continue
        row_attr = ""
        if isinstance(r, tuple) and len(r) == 2 and isinstance(r[0], dict):
            row_attr = " " + " ".join(f'{k}="{esc(v)}"' for k, v in r[0].items())
            r = r[1]
        cells = []
        for i, c in enumerate(r):
            c = "" if c is None else str(c)
            if c.startswith("<td"):
                cells.append(c)
            elif i < text_cols:
                cells.append(f'<td class="text">{c}</td>')
            else:
                cells.append(f"<td>{c}</td>")
        body.append(f"<tr{row_attr}>{''.join(cells)}</tr>")
    t = (
        f'<table class="{cls}"{attrs}><thead>{group_row}<tr>{head}</tr></thead>'
        f"<tbody>{''.join(body)}</tbody></table>"
    )
    return f'<div class="tablewrap">{t}</div>' if wrap else t


def missing(what: str, why: str = "") -> str:
    return f'<p class="missing">{esc(what)} not available{": " + esc(why) if why else ""}.</p>'


def kpi(label: str, value: str, cls: str = "") -> str:
    return f'<div class="kpi {cls}"><div class="k">{esc(label)}</div><div class="v">{value}</div></div>'


def decimate(
    x: np.ndarray, y_list: Sequence[np.ndarray], max_points: int
) -> tuple[np.ndarray, list[np.ndarray]]:
    """Keep at most ~max_points of a trace: per bucket the first sample plus the samples at
    the min and max of each y (peaks survive, unlike plain striding). Sorted by index."""
    n = len(x)
    if n <= max_points:
        return np.asarray(x), [np.asarray(y) for y in y_list]
    n_buckets = max(1, max_points // (1 + 2 * len(y_list)))
    size = -(-n // n_buckets)  # ceil: equal buckets, the last one padded
    starts = np.arange(0, n, size)
    keep = [starts, np.array([n - 1])]
    for y in y_list:
        y = np.asarray(y, dtype=float)
        n_pad = len(starts) * size - n  # < size: every bucket holds a real sample
        yy = np.concatenate([np.where(np.isnan(y), np.inf, y), np.full(n_pad, np.inf)]).reshape(-1, size)
        keep.append(starts + np.argmin(yy, axis=1))
        yy = np.concatenate([np.where(np.isnan(y), -np.inf, y), np.full(n_pad, -np.inf)]).reshape(-1, size)
        keep.append(starts + np.argmax(yy, axis=1))
    idx = np.unique(np.minimum(np.concatenate(keep).astype(int), n - 1))
    return np.asarray(x)[idx], [np.asarray(y)[idx] for y in y_list]


def arr(a: Any) -> dict[str, str] | list:
    """A numeric array for a figure spec as plotly.js's typed-array form (float32, base64):
    ~5.3 bytes per value instead of ~10-20 as decimal text. Non-numeric data stays a list."""
    x = np.asarray(a)
    if x.dtype.kind not in "fiub":
        return x.tolist()
    return {
        "dtype": "f4",
        "bdata": base64.b64encode(np.ascontiguousarray(x, dtype="<f4").tobytes()).decode("ascii"),
    }


def grid(
    nrows: int,
    ncols: int,
    titles: Sequence[str] = (),
    hspace: float = 0.05,
    vspace: float = 0.12,
    shared_y: bool = False,
) -> tuple[dict, list[tuple[str, str]]]:
    """Layout of an nrows x ncols grid of subplots for a dict figure spec (plotly.py's
    make_subplots costs ~0.2 s per call through its validators; this costs nothing).
    Returns (layout, [(xref, yref) per cell, row-major])."""
    layout: dict[str, Any] = {"annotations": []}
    refs = []
    w = (1.0 - hspace * (ncols - 1)) / ncols
    h = (1.0 - vspace * (nrows - 1)) / nrows
    for k in range(nrows * ncols):
        r, c = divmod(k, ncols)
        n = "" if k == 0 else str(k + 1)
        x0 = c * (w + hspace)
        y1 = 1.0 - r * (h + vspace)
        layout[f"xaxis{n}"] = {"domain": [x0, x0 + w], "anchor": f"y{n}"}
        layout[f"yaxis{n}"] = {"domain": [y1 - h, y1], "anchor": f"x{n}"}
        if shared_y and k > 0:
            layout[f"yaxis{n}"]["matches"] = "y"
            layout[f"yaxis{n}"]["showticklabels"] = False
        refs.append((f"x{n}", f"y{n}"))
        if k < len(titles):
            layout["annotations"].append(
                {
                    "text": titles[k],
                    "x": x0 + w / 2,
                    "y": y1,
                    "xref": "paper",
                    "yref": "paper",
                    "xanchor": "center",
                    "yanchor": "bottom",
                    "showarrow": False,
                    "font": {"size": 12},
                }
            )
    return layout, refs


def _json_default(o: Any) -> Any:
    if isinstance(o, np.ndarray):
        return arr(o)
    if isinstance(o, np.generic):
        return o.item()
    raise TypeError(f"not JSON serialisable: {type(o).__name__}")


class Page:
    """Collects figures and sections and renders one self-contained HTML document."""

    def __init__(self, title: str) -> None:
        self.title = title
        self.n_figures = 0

    def figure(self, fig: go.Figure | dict, height: int = 360, caption: str = "", name: str = "") -> str:
        """HTML for one figure: a div drawn by the runtime from the JSON that follows it."""
        self.n_figures += 1
        fid = f"fig{self.n_figures}"
        # a dict first: touching go.Figure makes plotly import its figure classes (~0.2 s),
        # and every report builds its figures as dicts
        if isinstance(fig, dict):
            spec = fig
        else:
            spec = json.loads(fig.to_json(validate=False))
        layout = dict(spec.get("layout", {}))
        layout.pop("template", None)
        layout.update(height=height, autosize=True)
        text = json.dumps(
            {"data": spec.get("data", []), "layout": layout},
            separators=(",", ":"),
            allow_nan=False,
            default=_json_default,
        )
        text = text.replace("<", "\\u003c").replace(">", "\\u003e")
        cap = f'<p class="note">{caption}</p>' if caption else ""
        return (
            f'<div class="figure" id="{fid}" data-spec="{fid}-spec" data-name="{esc(name)}" '
            f'style="height:{height}px"></div>'
            f'<script type="application/json" id="{fid}-spec">{text}</script>{cap}'
        )

    def render(self, header_html: str, body_html: str) -> str:
        runtime = _RUNTIME % {"template": json.dumps(_TEMPLATE, separators=(",", ":"))}
        generated = datetime.now(UTC).strftime("%Y-%m-%d %H:%M UTC")
        return (
            '<!DOCTYPE html>\n<html lang="en"><head><meta charset="utf-8">'
            '<meta name="viewport" content="width=device-width, initial-scale=1">'
            f"<title>{esc(self.title)}</title><style>{_CSS}</style>"
            f"<script>{plotly_js()}</script></head>"
            f'<body data-figures-total="{self.n_figures}">{header_html}<main>{body_html}</main>'
            f"<footer>mimucal report · generated {generated} · {self.n_figures} figures · "
            "self-contained (plotly.js embedded), works offline</footer>"
            f"<script>{runtime}</script></body></html>\n"
        )


@functools.lru_cache(maxsize=1)
def plotly_js() -> str:
    """plotly.js, read from plotly's package once per process (a 4.6 MB file)."""
    return get_plotlyjs()


def write_atomic(path, text: str) -> None:
    """Write a report via a temp file and rename, so a reader never sees half a file."""
    import os
    import tempfile
    from pathlib import Path

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "w", encoding="utf-8") as fh:
            fh.write(text)
        os.chmod(tmp, 0o644)
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise
