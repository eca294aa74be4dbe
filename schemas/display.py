"""How a stored quantity is shown to people: one table for the reports, the CLI summaries and
the Python API's printouts.

Values are stored in mimucal's inside units (deg/s, g, mm, deg, dimensionless ratios or
"<unit> per <raw unit>"). People read them in the units of datasheets:

- a value (a unit's mean): biases in g as **mg**, the rest as stored;
- a spread (standard deviation over repetitions, a lot's scatter, a standard error):
  dimensionless ratios (scale factors, misalignments) in **ppm**, gyro biases in **deg/h**,
  accelerometer biases in **mg**, the rest as stored.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

MINUS = "\u2212"


@dataclass(frozen=True)
class Shown:
    """A unit as shown: its label and the factor from the stored unit to it."""

    label: str
    factor: float


def is_dimensionless(uom: str | None) -> bool:
    """True for "" / "1" / "dimensionless" and ratios of a unit to itself ("deg/s per
    deg/s", "g/g")."""
    u = (uom or "").strip()
    if u in ("", "1", "-", "none", "dimensionless"):
        return True
    for sep in (" per ", "/"):
        parts = u.split(sep)
        if len(parts) == 2 and parts[0].strip() == parts[1].strip():
            return True
    return False


def value_unit(uom: str | None) -> Shown:
    """How a value (a mean) of a quantity stored in ``uom`` is shown."""
    u = (uom or "").strip()
    if is_dimensionless(u):
        return Shown("", 1.0)
    if u == "g":
        return Shown("mg", 1e3)
    return Shown(u, 1.0)


def spread_unit(uom: str | None) -> Shown:
    """How a spread (std, scatter, standard error) of a quantity stored in ``uom`` is shown."""
    u = (uom or "").strip()
    if is_dimensionless(u):
        return Shown("ppm", 1e6)
    if u == "g":
        return Shown("mg", 1e3)
    if u == "deg/s":
        return Shown("deg/h", 3600.0)
    return Shown(u, 1.0)


def decimals_for(scale: float | None, extra: int = 1, max_decimals: int = 8) -> int | None:
    """Decimals so that a quantity of size ``scale`` (a spread or stderr) shows ``1 + extra``
    significant digits; None when the scale is unknown."""
    if scale is None or not math.isfinite(scale) or scale <= 0:
        return None
    return int(min(max(extra - math.floor(math.log10(scale)), 0), max_decimals))


def number(x: float | None, decimals: int | None = None, sig: int = 5, minus: str = "-") -> str:
    """``x`` with ``decimals`` fixed decimals, else ``sig`` significant digits; "-" when
    missing or not finite."""
    try:
        v = float(x)  # type: ignore[arg-type]
    except (TypeError, ValueError):
        return "-"
    if not math.isfinite(v):
        return "-"
    s = f"{v:.{decimals}f}" if decimals is not None else f"{v:.{sig}g}"
    return minus + s[1:] if s.startswith("-") else s


def spread_text(std: float | None, uom: str | None, sig: int = 2) -> str:
    """A spread in its shown unit with ``sig`` significant digits, e.g. "8.8 ppm"."""
    shown = spread_unit(uom)
    try:
        v = float(std) * shown.factor  # type: ignore[arg-type]
    except (TypeError, ValueError):
        return "-"
    if not math.isfinite(v):
        return "-"
    text = f"{v:.{sig}g}" if abs(v) < 10**sig else f"{v:.0f}"
    return f"{text} {shown.label}".rstrip()


def value_text(mean: float | None, uom: str | None, std: float | None = None) -> str:
    """A value in its shown unit with as many decimals as its spread ``std`` supports (one
    digit more than the spread's first), else 6 significant digits."""
    shown = value_unit(uom)
    try:
        v = float(mean) * shown.factor  # type: ignore[arg-type]
    except (TypeError, ValueError):
        return "-"
    dec = None
    if std is not None:
        try:
            dec = decimals_for(float(std) * shown.factor, extra=1)
        except (TypeError, ValueError):
            dec = None
    text = number(v, dec, sig=6)
    return f"{text} {shown.label}".rstrip()
