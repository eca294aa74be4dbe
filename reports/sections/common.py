"""HTML pieces several sections share: flag badges, parameter symbols, legend placement."""

from __future__ import annotations

from typing import Any

from calib_core.models.display import param_symbol
from reports.context import (
    KIND_LIMITS,
    KIND_OUTLIER,
)
from reports.html import (
    esc,
)


def kind_badges(kinds: set[str], count: int | None = None) -> str:
    """The badges of a unit or parameter: limits failed, outlier, or both."""
    n = f"{count} " if count else ""
    out = []
    if KIND_LIMITS in kinds:
        out.append(f'<span class="badge limit">✖ {n}limit failed</span>')
    if KIND_OUTLIER in kinds:
        out.append(f'<span class="badge flag">⚑ {"" if KIND_LIMITS in kinds else n}outlier</span>')
    return " ".join(out)


def qa_badge(status: Any) -> str:
    """The badge of a calibration file's QA status (pass / flagged / limits / not judged)."""
    if status == "pass":
        return '<span class="badge ok">pass</span>'
    if status == "flagged":
        return '<span class="badge flag">⚑ outlier</span>'
    if status == "limits":
        return '<span class="badge limit">✖ limits</span>'
    return '<span class="badge unjudged">not judged</span>'


def pretty_param(name: str) -> str:
    """A parameter's symbol as its model declares it (``k_g11``: k with subscript g11), else
    its name."""
    sym = param_symbol(name)
    if sym is None:
        return esc(str(name))
    return f"{sym[0]}<sub>{sym[1]}</sub>"


def legend_top(y: float = 1.0) -> dict:
    return {"orientation": "h", "y": y, "x": 1.0, "xanchor": "right", "yanchor": "bottom"}
