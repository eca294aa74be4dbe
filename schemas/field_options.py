"""The data rules of a field recording's options (shared by the nightly's field units and
``mimucal field``): where an int16 output clips, the seconds at rest at the start, and the
starting scales of the fit from the options or the sensor's full-scale ranges."""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import Any

from schemas.importers import FULL_SCALE_COUNTS, parse_range

INIT_PREAMBLE_KEYS = ("initialization time", "init time", "initial rest", "tinit")
INT16_LIMIT = 32767.0  # an int16 output clips here
STANDARD_GRAVITY = 9.80665  # m/s^2, the starting g when the options give none


def init_static_s(opts: Mapping[str, Any], preamble: Mapping[str, str]) -> float | None:
    """Seconds at rest at the start: the ``init_static`` option (0: none), else the log's
    preamble ``Initialization time`` line, else None (the detector uses the quietest
    windows)."""
    v = opts.get("init_static")
    if v is not None:
        return float(v) if v > 0 else None
    for key, value in preamble.items():
        if key.strip().lower() in INIT_PREAMBLE_KEYS:
            try:
                return float(value)
            except ValueError:
                return None
    return None


def clip_limit(opts: Mapping[str, Any]) -> float | None:
    """Where the gyro output clips: the int16 limit when a full-scale range says the data
    are raw counts, else None (no clipping known)."""
    return INT16_LIMIT if opts.get("gyro_range") else None


def starting_scales(
    opts: Mapping[str, Any], gyro_unit: str, accel_unit: str
) -> tuple[float | None, float | None]:
    """Starting accel scale (m/s^2 per raw unit) and gyro scale (rad/s per raw unit): the
    ``acc_scale``/``gyro_scale`` options, else the int16 full-scale ranges, else identity
    for data already in g / deg/s. ValueError when a range is given for physical units or
    does not parse."""
    acc, gyr = opts.get("acc_scale"), opts.get("gyro_scale")
    g_local = float(opts.get("g_local") or STANDARD_GRAVITY)
    if acc is None and opts.get("accel_range"):
        if accel_unit != "LSB":
            raise ValueError("--accel-range applies to raw counts (--accel-unit LSB)")
        acc = parse_range(opts["accel_range"], "accel") * g_local / FULL_SCALE_COUNTS
    if gyr is None and opts.get("gyro_range"):
        if gyro_unit != "LSB":
            raise ValueError("--gyro-range applies to raw counts (--gyro-unit LSB)")
        gyr = math.radians(parse_range(opts["gyro_range"], "gyro") / FULL_SCALE_COUNTS)
    if acc is None and accel_unit == "g":  # already physical: identity is the start
        acc = g_local
    if gyr is None and gyro_unit == "deg/s":
        gyr = math.radians(1.0)
    return acc, gyr
