"""The input contract (shared/spec/acquisition-format.md) as code: Parquet schemas of
``steps.parquet`` and ``samples.parquet``, the types each column may have, the allowed units,
tests and up axes, and the key-value metadata with its parsing.

Types: the schemas below are what :mod:`schemas.writer` writes. The reader is a little more
lenient than the schema where nothing can be lost, and says so here, in one place:

- ``step`` (both files): any integer width (``int32`` in the contract; ``int64`` is what
  pandas writes by default); cast to int32 after a range check.
- string columns: ``string``, ``large_string`` or dictionary-encoded strings.
- float64 columns of steps.parquet: any float or integer type (cast to float64);
  ``angle_deg`` may also be an all-null column.
- ``t``: float64 or float32. Sensor columns ``gx..az``: float32 or float64 (the contract).
  ``temp_c``: optional, float32 or float64.

Extra columns are allowed in both files and never read (column projection).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field

import pyarrow as pa

from calib_core.steps import TESTS, UP_AXES
from schemas.errors import E_BAD_METADATA, E_MISSING_COLUMN, E_UNKNOWN_UNIT, E_WRONG_TYPE, SessionError

STEPS_FILE = "steps.parquet"
SAMPLES_FILE = "samples.parquet"

# --- schemas (what the writer writes) ------------------------------------------------------
STEPS_SCHEMA = pa.schema(
    [
        ("step", pa.int32()),
        ("test", pa.string()),
        ("up_axis", pa.string()),
        ("rate_dps", pa.float64()),
        ("angle_deg", pa.float64()),
        ("w_ref_x", pa.float64()),
        ("w_ref_y", pa.float64()),
        ("w_ref_z", pa.float64()),
        ("f_ref_x", pa.float64()),
        ("f_ref_y", pa.float64()),
        ("f_ref_z", pa.float64()),
        ("settle_s", pa.float64()),
    ]
)
# optional steps columns, never required: duration_s (written by mimucal), heading_deg (the
# step's heading, degrees, added to table_heading_deg: docs/data-contract.md)
STEPS_OPTIONAL = {"duration_s": pa.float64(), "heading_deg": pa.float64()}

GYRO_COLUMNS = ("gx", "gy", "gz")
ACCEL_COLUMNS = ("ax", "ay", "az")
SENSOR_COLUMNS = GYRO_COLUMNS + ACCEL_COLUMNS
SAMPLES_SCHEMA = pa.schema(
    [("step", pa.int32()), ("t", pa.float64())] + [(c, pa.float32()) for c in SENSOR_COLUMNS]
)
SAMPLES_OPTIONAL = {"temp_c": pa.float32()}

W_REF_COLUMNS = ("w_ref_x", "w_ref_y", "w_ref_z")
F_REF_COLUMNS = ("f_ref_x", "f_ref_y", "f_ref_z")
STEP_FLOAT_COLUMNS = ("rate_dps", "angle_deg") + W_REF_COLUMNS + F_REF_COLUMNS + ("settle_s",)

# --- allowed values --------------------------------------------------------------------------
GYRO_UNITS = ("deg/s", "rad/s", "LSB", "V")
ACCEL_UNITS = ("g", "m/s^2", "LSB", "V")
RAW_UNITS = ("LSB", "V")  # kept raw: the fitted matrices absorb them
ALLOWED_TESTS = TESTS
ALLOWED_UP_AXES = UP_AXES
G_LOCAL_DEFAULT = 9.80665
G_LOCAL_PLAUSIBLE = (9.70, 9.90)  # m/s^2 anywhere on Earth's surface (about 9.76-9.84)
RAD_TO_DEG = 180.0 / math.pi
# a session_start outside these years is a typo or hostile: refused (E_BAD_METADATA) before a
# date reaches pandas (nanosecond timestamps end in 2262) or the store's tables
SESSION_START_YEARS = (1970, 2200)

REQUIRED_METADATA = ("gyro_unit", "accel_unit", "gyro_range_dps", "accel_range_g")
# provenance keys that are pyarrow/pandas internals, not the acquisition system's
INTERNAL_METADATA = ("pandas", "ARROW:schema")


# --- column types ----------------------------------------------------------------------------
def _is_string(t: pa.DataType) -> bool:
    if pa.types.is_dictionary(t):
        t = t.value_type
    return pa.types.is_string(t) or pa.types.is_large_string(t)


def _is_float(t: pa.DataType) -> bool:
    return pa.types.is_float32(t) or pa.types.is_float64(t)


def _is_number(t: pa.DataType) -> bool:
    return pa.types.is_floating(t) or pa.types.is_integer(t)


@dataclass(frozen=True)
class ColumnRule:
    name: str
    accepts: Callable[[pa.DataType], bool]
    expected: str  # what the message says is expected
    required: bool = True


STEPS_RULES = (
    ColumnRule("step", pa.types.is_integer, "int32"),
    ColumnRule("test", _is_string, "string"),
    ColumnRule("up_axis", _is_string, "string"),
    *(
        ColumnRule(c, _is_number, "float64")
        for c in ("rate_dps",) + W_REF_COLUMNS + F_REF_COLUMNS + ("settle_s",)
    ),
    ColumnRule("angle_deg", lambda t: _is_number(t) or pa.types.is_null(t), "float64 (nullable)"),
)
SAMPLES_RULES = (
    ColumnRule("step", pa.types.is_integer, "int32"),
    ColumnRule("t", _is_float, "float64"),
    *(ColumnRule(c, _is_float, "float32 or float64") for c in SENSOR_COLUMNS),
    ColumnRule("temp_c", _is_float, "float32", required=False),
)


def check_columns(schema: pa.Schema, rules: tuple[ColumnRule, ...], session: str, file: str) -> list[str]:
    """Raise E_MISSING_COLUMN / E_WRONG_TYPE; return the contract columns present (the
    projection to read)."""
    all_names = schema.names  # a new list at every access: taken once
    present = set(all_names)
    for rule in rules:
        if rule.required and rule.name not in present:
            raise SessionError(
                E_MISSING_COLUMN,
                session,
                file,
                f"required column '{rule.name}' is missing (columns present: "
                f"{', '.join(all_names) or 'none'})",
                column=rule.name,
            )
    names = []
    for rule in rules:
        if rule.name not in present:
            continue
        if all_names.count(rule.name) > 1:
            raise SessionError(
                E_WRONG_TYPE, session, file, f"column '{rule.name}' appears more than once", column=rule.name
            )
        dtype = schema.field(rule.name).type
        if not rule.accepts(dtype):
            raise SessionError(
                E_WRONG_TYPE,
                session,
                file,
                f"column '{rule.name}' has type {dtype}, expected {rule.expected}",
                column=rule.name,
            )
        names.append(rule.name)
    return names


# --- metadata --------------------------------------------------------------------------------
@dataclass(frozen=True)
class SessionMeta:
    """Parsed key-value metadata of samples.parquet.

    ``gyro_unit``/``accel_unit`` are the units *inside* mimucal after boundary conversion
    (rad/s -> deg/s, m/s^2 -> g); ``*_unit_raw`` what the file declares; ``*_scale`` the factor
    that converts file values to inside values.
    """

    gyro_unit_raw: str
    accel_unit_raw: str
    gyro_range_dps: tuple[float, float, float]
    accel_range_g: tuple[float, float, float]
    g_local: float = G_LOCAL_DEFAULT
    sample_rate_hz: float | None = None
    session_start: str | None = None
    gyro_full_scale_raw: tuple[float, float, float] | None = None
    accel_full_scale_raw: tuple[float, float, float] | None = None
    provenance: dict[str, str] = field(default_factory=dict)
    latitude_deg: float | None = None  # of the turntable, degrees north (Earth rate)
    table_heading_deg: float | None = None  # of the table's zero-heading reference, deg E of N

    @property
    def gyro_unit(self) -> str:
        return "deg/s" if self.gyro_unit_raw == "rad/s" else self.gyro_unit_raw

    @property
    def accel_unit(self) -> str:
        return "g" if self.accel_unit_raw == "m/s^2" else self.accel_unit_raw

    @property
    def gyro_scale(self) -> float:
        return RAD_TO_DEG if self.gyro_unit_raw == "rad/s" else 1.0

    @property
    def accel_scale(self) -> float:
        return 1.0 / self.g_local if self.accel_unit_raw == "m/s^2" else 1.0

    @property
    def gyro_is_physical(self) -> bool:
        return self.gyro_unit_raw not in RAW_UNITS

    @property
    def accel_is_physical(self) -> bool:
        return self.accel_unit_raw not in RAW_UNITS


def decode_metadata(raw: Mapping | None) -> dict[str, str]:
    """Parquet schema metadata (bytes -> bytes) as str -> str, without pyarrow/pandas internals."""
    out: dict[str, str] = {}
    for k, v in (raw or {}).items():
        k = k.decode("utf-8", "replace") if isinstance(k, bytes) else str(k)
        v = v.decode("utf-8", "replace") if isinstance(v, bytes) else str(v)
        if k not in INTERNAL_METADATA:
            out[k] = v
    return out


def parse_triple(
    text: str, key: str, session: str, file: str, positive: bool = True
) -> tuple[float, float, float]:
    """``"300,300,3600"`` -> (300.0, 300.0, 3600.0); one value is used for all three axes."""
    parts = [p.strip() for p in str(text).split(",")]
    try:
        values = [float(p) for p in parts]
    except ValueError:
        raise SessionError(
            E_BAD_METADATA,
            session,
            file,
            f"metadata '{key}' = {text!r} is not a comma-separated list of "
            f"numbers (expected e.g. '300,300,3600')",
        ) from None
    if len(values) == 1:
        values = values * 3
    if len(values) != 3:
        raise SessionError(
            E_BAD_METADATA,
            session,
            file,
            f"metadata '{key}' = {text!r} has {len(values)} values, expected 3 (x,y,z)",
        )
    if not all(math.isfinite(v) and (v > 0 or not positive) for v in values):
        raise SessionError(
            E_BAD_METADATA, session, file, f"metadata '{key}' = {text!r} must be finite and positive"
        )
    return (values[0], values[1], values[2])


def _parse_positive(text: str, key: str, session: str, file: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise SessionError(
            E_BAD_METADATA, session, file, f"metadata '{key}' = {text!r} is not a number"
        ) from None
    if not (math.isfinite(value) and value > 0):
        raise SessionError(
            E_BAD_METADATA, session, file, f"metadata '{key}' = {text!r} must be finite and positive"
        )
    return value


def session_start_problem(text: object) -> str | None:
    """Why ``text`` is not a usable ``session_start`` (ISO 8601 date-time, years
    :data:`SESSION_START_YEARS`), or None when it is."""
    from datetime import datetime

    if not isinstance(text, str) or len(text) > 64:
        return "is not an ISO 8601 date-time (e.g. 2026-11-20T02:00:00Z)"
    try:
        dt = datetime.fromisoformat(text.strip().replace("Z", "+00:00"))
    except ValueError:
        return f"{text[:40]!r} is not an ISO 8601 date-time (e.g. 2026-11-20T02:00:00Z)"
    lo, hi = SESSION_START_YEARS
    if not lo <= dt.year < hi:
        return f"{text[:40]!r} is outside the years {lo}-{hi - 1}"
    return None


def _checked_session_start(text: str | None, session: str, file: str) -> str | None:
    if text is None or not str(text).strip():
        return None
    why = session_start_problem(text)
    if why:
        raise SessionError(E_BAD_METADATA, session, file, f"metadata 'session_start' {why}")
    return text


def parse_metadata(raw: Mapping | None, session: str, file: str = SAMPLES_FILE) -> SessionMeta:
    """Validate and parse the key-value metadata of samples.parquet (E_BAD_METADATA,
    E_UNKNOWN_UNIT). Unknown keys are kept as provenance."""
    md = decode_metadata(raw)
    for key in REQUIRED_METADATA:
        if key not in md or not md[key].strip():
            raise SessionError(
                E_BAD_METADATA,
                session,
                file,
                f"metadata key '{key}' is missing (required: {', '.join(REQUIRED_METADATA)})",
            )
    gyro_unit = md["gyro_unit"].strip()
    accel_unit = md["accel_unit"].strip()
    if gyro_unit not in GYRO_UNITS:
        raise SessionError(
            E_UNKNOWN_UNIT,
            session,
            file,
            f"gyro_unit {md['gyro_unit']!r} is not one of {', '.join(GYRO_UNITS)}",
        )
    if accel_unit not in ACCEL_UNITS:
        raise SessionError(
            E_UNKNOWN_UNIT,
            session,
            file,
            f"accel_unit {md['accel_unit']!r} is not one of {', '.join(ACCEL_UNITS)}",
        )
    g_local = G_LOCAL_DEFAULT
    if md.get("g_local", "").strip():
        g_local = _parse_positive(md["g_local"], "g_local", session, file)
        lo, hi = G_LOCAL_PLAUSIBLE
        if not lo <= g_local <= hi:
            raise SessionError(
                E_BAD_METADATA,
                session,
                file,
                f"metadata 'g_local' = {md['g_local']!r} m/s^2 is outside "
                f"{lo}-{hi} m/s^2 (local gravity in m/s^2, not g)",
            )
    rate = None
    if md.get("sample_rate_hz", "").strip():
        rate = _parse_positive(md["sample_rate_hz"], "sample_rate_hz", session, file)
    fs_g = fs_a = None
    if md.get("gyro_full_scale_raw", "").strip():
        fs_g = parse_triple(md["gyro_full_scale_raw"], "gyro_full_scale_raw", session, file)
    if md.get("accel_full_scale_raw", "").strip():
        fs_a = parse_triple(md["accel_full_scale_raw"], "accel_full_scale_raw", session, file)
    location = {}
    for key, bound in (("latitude_deg", 90.0), ("table_heading_deg", 360.0)):
        if md.get(key, "").strip():
            try:
                value = float(md[key])
            except ValueError:
                raise SessionError(
                    E_BAD_METADATA, session, file, f"metadata '{key}' = {md[key]!r} is not a number"
                ) from None
            if not (math.isfinite(value) and abs(value) <= bound):
                raise SessionError(
                    E_BAD_METADATA,
                    session,
                    file,
                    f"metadata '{key}' = {md[key]!r} must be within +/-{bound:g} degrees",
                )
            location[key] = value
    return SessionMeta(
        gyro_unit_raw=gyro_unit,
        accel_unit_raw=accel_unit,
        gyro_range_dps=parse_triple(md["gyro_range_dps"], "gyro_range_dps", session, file),
        accel_range_g=parse_triple(md["accel_range_g"], "accel_range_g", session, file),
        g_local=g_local,
        sample_rate_hz=rate,
        session_start=_checked_session_start(md.get("session_start"), session, file),
        gyro_full_scale_raw=fs_g,
        accel_full_scale_raw=fs_a,
        provenance=md,
        **location,
    )
