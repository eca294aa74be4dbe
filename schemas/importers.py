"""Importers for recordings made without a turntable (Ferraris sessions, hand-moved
multi-position sessions), from CSV or whitespace-separated text exports of any IMU.

In-memory layout (the sibling of the acquisition contract for sessions without references):
:class:`RawRecording` holds one DataFrame ``samples`` with columns

    t [s since the first sample], gx gy gz [gyro_unit], ax ay az [accel_unit]

and the units after boundary conversion, exactly as in the contract: gyro ``deg/s`` (``rad/s``
input is converted to deg/s) or a raw unit (``LSB``; ``counts`` is an alias; ``V``); accel
``g`` (``m/s^2`` input is divided by the recording's ``g_local``; ``mg`` is divided by 1000) or
raw (``LSB``, ``V``). There is no ``step`` column and no reference: the calibration methods
that consume these recordings (:mod:`calib_core.models.ferraris`,
:mod:`calib_core.models.field.imu_tk`) find the static poses themselves or take a section list.

Errors are :class:`schemas.errors.SessionError` naming the file (the "session" is the file
name: these recordings have no lot/unit/rep).
"""

from __future__ import annotations

import io
import json
import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from schemas.errors import (
    E_MISSING_COLUMN,
    E_MISSING_FILE,
    E_NONFINITE_VALUE,
    E_NONINCREASING_TIME,
    E_UNKNOWN_UNIT,
    E_UNREADABLE_FILE,
    E_WRONG_TYPE,
    SessionError,
)

CHANNELS = ("gx", "gy", "gz", "ax", "ay", "az")
GYRO_CHANNELS = CHANNELS[:3]
ACCEL_CHANNELS = CHANNELS[3:]

# input unit -> (unit after conversion, factor applied)
GYRO_INPUT_UNITS: dict[str, tuple[str, float]] = {
    "deg/s": ("deg/s", 1.0),
    "dps": ("deg/s", 1.0),
    "rad/s": ("deg/s", 180.0 / math.pi),
    "LSB": ("LSB", 1.0),
    "counts": ("LSB", 1.0),
    "V": ("V", 1.0),
}
ACCEL_INPUT_UNITS = ("g", "mg", "m/s^2", "m/s2", "LSB", "counts", "V")

IMUCAL_RATE_HZ = 102.4  # imucal's example session (README of shared/data/real/imucal)
IMUCAL_G = 9.81  # the gravity imucal's FerrarisCalibration uses (its default ``grav``)
IMUTK_G = 9.81744  # local gravity of IMU-TK's demo (test_imu_calib)


@dataclass(frozen=True)
class RawRecording:
    """A recording without turntable references, in the documented in-memory layout."""

    samples: pd.DataFrame  # t, gx gy gz, ax ay az (float64)
    gyro_unit: str  # deg/s | LSB | V (after conversion)
    accel_unit: str  # g | LSB | V (after conversion)
    g_local: float  # m/s^2, used to convert m/s^2 input to g and back on output
    rate_hz: float  # nominal sample rate
    source: str  # file name(s), used in messages
    metadata: dict[str, Any] = field(default_factory=dict)

    @property
    def t(self) -> np.ndarray:
        return self.samples["t"].to_numpy()

    @property
    def gyro(self) -> np.ndarray:
        return self.samples[list(GYRO_CHANNELS)].to_numpy()

    @property
    def accel(self) -> np.ndarray:
        return self.samples[list(ACCEL_CHANNELS)].to_numpy()

    def __len__(self) -> int:
        return len(self.samples)


def _err(code: str, path: Path | str, reason: str, column: str | None = None) -> SessionError:
    return SessionError(code, Path(path).name, str(path), reason, column=column)


def convert_gyro(values: np.ndarray, unit: str, path: Path | str = "<array>") -> tuple[np.ndarray, str]:
    if unit not in GYRO_INPUT_UNITS:
        raise _err(E_UNKNOWN_UNIT, path, f"gyro unit {unit!r} is not one of {', '.join(GYRO_INPUT_UNITS)}")
    out_unit, factor = GYRO_INPUT_UNITS[unit]
    return np.asarray(values, float) * factor, out_unit


def convert_accel(
    values: np.ndarray, unit: str, g_local: float, path: Path | str = "<array>"
) -> tuple[np.ndarray, str]:
    values = np.asarray(values, float)
    if unit == "g":
        return values, "g"
    if unit == "mg":
        return values / 1000.0, "g"
    if unit in ("m/s^2", "m/s2"):
        return values / g_local, "g"
    if unit in ("LSB", "counts"):
        return values, "LSB"
    if unit == "V":
        return values, "V"
    raise _err(E_UNKNOWN_UNIT, path, f"accel unit {unit!r} is not one of {', '.join(ACCEL_INPUT_UNITS)}")


def accel_from_g(values: np.ndarray, unit: str, g_local: float) -> np.ndarray:
    """Specific force in g back to ``unit`` (g, mg or m/s^2 with ``g_local``): the inverse
    of :func:`convert_accel`, for outputs written in the input's unit."""
    values = np.asarray(values, float)
    if unit == "g":
        return values
    if unit == "mg":
        return values * 1000.0
    if unit in ("m/s^2", "m/s2"):
        return values * g_local
    raise ValueError(f"specific force in g cannot be written in {unit!r}")


FULL_SCALE_COUNTS = 32768.0  # a signed 16-bit output: +/- full scale is +/- 32768 counts


def parse_range(text: str, kind: str) -> float:
    """Full-scale range of a sensor, ``"2g"``/``"16g"`` (accel, in g) or ``"250dps"``/
    ``"250deg/s"`` (gyro, in deg/s). The starting scale of an int16 output is
    ``range / 32768`` per count (e.g. 2 g -> 16384 counts per g, 250 deg/s -> 131.07)."""
    t = text.strip().lower().replace(" ", "")
    suffixes = {"accel": ("g",), "gyro": ("dps", "deg/s", "°/s")}[kind]
    for suf in suffixes:
        if t.endswith(suf):
            try:
                value = float(t[: -len(suf)])
            except ValueError:
                break
            if 0 < value <= 1e6:  # finite: "infg" is no full scale
                return value
    unit = "g, e.g. 2g" if kind == "accel" else "deg/s, e.g. 250dps"
    raise ValueError(f"{kind} range {text!r} is not a positive full scale in {unit}")


def auto_column_mapping(columns) -> dict[str, str] | None:
    """{channel: column} when the header names the six channels itself (``ax,ay,az,gx,gy,gz``
    in any order and case, optionally a time column ``t``/``time``), else None."""
    lower = {str(c).strip().lower(): str(c) for c in columns}
    if not all(ch in lower for ch in CHANNELS):
        return None
    mapping = {ch: lower[ch] for ch in CHANNELS}
    for name in ("t", "time", "timestamp"):
        if name in lower:
            mapping["t"] = lower[name]
            break
    return mapping


def parse_column_mapping(text: str) -> dict[str, str]:
    """``"gx=gyr_x,gy=gyr_y,...,t=time"`` -> {channel: source column}. Source columns of a
    header-less whitespace file are their 0-based positions (``gx=1``)."""
    mapping: dict[str, str] = {}
    for part in filter(None, (p.strip() for p in text.split(","))):
        if "=" not in part:
            raise ValueError(f"column mapping item {part!r} is not CHANNEL=SOURCE")
        key, src = (s.strip() for s in part.split("=", 1))
        if key not in CHANNELS + ("t",):
            raise ValueError(f"column mapping: {key!r} is not one of t, {', '.join(CHANNELS)}")
        mapping[key] = src
    return mapping


COMMENT_PREFIXES = ("#", "//", "%")


def _is_number(token: str) -> bool:
    try:
        float(token)
        return True
    except ValueError:
        return False


def _split(line: str, sep: str | None) -> list[str]:
    return [x.strip() for x in (line.split(sep) if sep else line.split())]


@dataclass(frozen=True)
class TableLayout:
    """Where the data of a text log start: separator (``None`` = whitespace), 1-based line of
    the header (0 when there is none), 1-based line of the first data row, the column names,
    and the ``key,value`` preamble lines before the header (e.g. ``Fs,100``)."""

    sep: str | None
    header_line: int
    data_line: int
    columns: list[str]
    preamble: dict[str, str]


def sniff_table(path: Path, max_lines: int = 200) -> TableLayout:
    """Find the layout of a text log from its first lines: blank and comment lines (``#``,
    ``//``, ``%``) are skipped; the first line whose fields are all numbers, followed by a
    line with as many numeric fields, starts the data; the non-numeric line just before it
    with the same field count is the header; anything earlier is the preamble (``key,value``
    pairs are kept)."""
    lines: list[tuple[int, str]] = []
    with path.open() as fh:
        for no, raw in enumerate(fh, start=1):
            line = raw.strip()
            if line and not line.startswith(COMMENT_PREFIXES):
                lines.append((no, line))
            if len(lines) >= max_lines:
                break
    if not lines:
        raise _err(E_UNREADABLE_FILE, path, "no data lines (empty or only comments)")

    def sep_of(line: str) -> str | None:
        for sep in (",", ";", "\t"):
            if sep in line:
                return sep
        return None

    for i in range(len(lines)):
        no, line = lines[i]
        sep = sep_of(line)
        fields = _split(line, sep)
        if not all(_is_number(x) for x in fields):
            continue
        if i + 1 < len(lines):
            nxt = _split(lines[i + 1][1], sep)
            if len(nxt) != len(fields) or not all(_is_number(x) for x in nxt):
                continue
        header_line, columns = 0, [str(k) for k in range(len(fields))]
        first_pre = i
        if i > 0:
            hno, hline = lines[i - 1]
            hfields = _split(hline, sep)
            if len(hfields) == len(fields):
                header_line, columns, first_pre = hno, hfields, i - 1
        preamble = {}
        for _, pline in lines[:first_pre]:
            kv = _split(pline, sep_of(pline))
            if len(kv) == 2:
                preamble[kv[0]] = kv[1]
        return TableLayout(sep, header_line, no, columns, preamble)
    no, line = lines[-1]
    raise _err(
        E_UNREADABLE_FILE,
        path,
        f"line {no}: no two consecutive lines of numbers found "
        f"in the first {max_lines} lines (last read: {line[:60]!r})",
    )


def _first_bad_line(path: Path, layout: TableLayout) -> str:
    """Reason naming the first data line that does not have the layout's number of numeric
    fields (only run when parsing failed, so a plain Python scan is fine)."""
    n = len(layout.columns)
    with path.open() as fh:
        for no, raw in enumerate(fh, start=1):
            line = raw.strip()
            if no < layout.data_line or not line or line.startswith(COMMENT_PREFIXES):
                continue
            fields = _split(line, layout.sep)
            if len(fields) != n:
                return f"line {no}: {len(fields)} fields, expected {n} ({line[:60]!r})"
            bad = [x for x in fields if not _is_number(x)]
            if bad:
                return f"line {no}: {bad[0][:30]!r} is not a number"
    return "no bad line found"


def _read_table(path: Path) -> pd.DataFrame:
    """A text log: optional preamble, comments, optional header, then rows of numbers
    separated by commas, semicolons, tabs or whitespace (:func:`sniff_table`). The preamble
    is in ``df.attrs["preamble"]``; a line that does not parse is named in the error."""
    if not path.exists():
        raise _err(E_MISSING_FILE, path, "no such file")
    try:
        layout = sniff_table(path)
    except (OSError, UnicodeDecodeError) as exc:
        raise _err(E_UNREADABLE_FILE, path, f"cannot read as text ({exc})") from exc
    try:
        with path.open() as fh:  # drop comment lines anywhere (pandas knows only one prefix)
            body = [
                ln
                for no, ln in enumerate(fh, start=1)
                if no >= layout.data_line and ln.strip() and not ln.lstrip().startswith(COMMENT_PREFIXES)
            ]
        df = pd.read_csv(
            io.StringIO("".join(body)),
            sep=layout.sep if layout.sep else r"\s+",
            header=None,
            names=layout.columns,
            engine="c",
            dtype=float,
        )
    except (ValueError, pd.errors.ParserError, pd.errors.EmptyDataError, UnicodeDecodeError) as exc:
        raise _err(E_UNREADABLE_FILE, path, _first_bad_line(path, layout)) from exc
    if df.isna().any().any():  # a short row is padded with NaN by the parser
        reason = _first_bad_line(path, layout)
        if reason != "no bad line found":  # else a literal nan: named by _numeric_column
            raise _err(E_UNREADABLE_FILE, path, reason)
    df.attrs["preamble"] = layout.preamble
    df.attrs["data_line"] = layout.data_line
    return df


def _numeric_column(df: pd.DataFrame, src: str, path: Path, channel: str) -> np.ndarray:
    if src not in df.columns:
        raise _err(
            E_MISSING_COLUMN,
            path,
            f"column {src[:40]!r} (for {channel}) not found; columns are "
            + ", ".join(repr(str(c)[:24]) for c in list(df.columns)[:12])
            + (f" and {len(df.columns) - 12} more" if len(df.columns) > 12 else ""),
            column=src,
        )
    try:
        values = pd.to_numeric(df[src], errors="raise").to_numpy(dtype=float)
    except (ValueError, TypeError) as exc:
        raise _err(E_WRONG_TYPE, path, f"column {src!r} is not numeric ({exc})", column=src) from exc
    bad = ~np.isfinite(values)
    if bad.any():
        raise _err(
            E_NONFINITE_VALUE,
            path,
            f"{int(bad.sum())} non-finite values in column {src!r}, first at row {int(np.argmax(bad))}",
            column=src,
        )
    return values


def _time_axis(
    values: np.ndarray | None, n: int, rate_hz: float | None, path: Path
) -> tuple[np.ndarray, float]:
    if values is None:
        if not rate_hz or rate_hz <= 0:
            raise _err(
                E_MISSING_COLUMN, path, "no time column mapped: give the sample rate (--rate)", column="t"
            )
        return np.arange(n) / float(rate_hz), float(rate_hz)
    if n > 1 and not (np.diff(values) > 0).all():
        i = int(np.argmax(np.diff(values) <= 0))
        raise _err(E_NONINCREASING_TIME, path, f"time not strictly increasing at row {i + 1}", column="t")
    t = values - values[0]
    est = (n - 1) / t[-1] if n > 1 and t[-1] > 0 else float("nan")
    return t, float(rate_hz) if rate_hz else est


PREAMBLE_RATE_KEYS = ("fs", "sample rate", "sampling rate", "rate", "rate_hz")


def preamble_rate(preamble: Mapping[str, str]) -> float | None:
    """The sample rate a logger wrote in its preamble (``Fs,100``), if any."""
    for key, value in preamble.items():
        if key.strip().lower() in PREAMBLE_RATE_KEYS:
            try:
                rate = float(value)
            except ValueError:
                return None
            return rate if rate > 0 else None
    return None


def read_table_recording(
    path: Path | str,
    columns: Mapping[str, str] | None,
    gyro_unit: str,
    accel_unit: str,
    rate_hz: float | None = None,
    g_local: float = 9.80665,
    time_scale: float = 1.0,
) -> RawRecording:
    """Generic importer: any CSV/whitespace text log (preamble, comments and header found by
    :func:`sniff_table`) with a column mapping {channel: column}.

    ``columns`` must map gx..az, or be None when the header names them (``ax,...,gz``);
    ``t`` is optional (then the rate is ``rate_hz``, else the preamble's ``Fs``, and
    ``t = row / rate``). ``time_scale`` multiplies the time column (e.g. 1e-3 for ms). The
    preamble's ``key,value`` pairs are kept in ``metadata["preamble"]``."""
    path = Path(path)
    df = _read_table(path)
    if columns is None:
        columns = auto_column_mapping(df.columns)
        if columns is None:
            raise _err(
                E_MISSING_COLUMN,
                path,
                "the header does not name ax,ay,az,gx,gy,gz: give "
                f"--columns (columns are {', '.join(map(str, df.columns))})",
            )
    missing = [c for c in CHANNELS if c not in columns]
    if missing:
        raise _err(E_MISSING_COLUMN, path, f"column mapping lacks {', '.join(missing)}")
    preamble = dict(df.attrs.get("preamble", {}))
    if rate_hz is None and "t" not in columns:
        rate_hz = preamble_rate(preamble)
    data = {ch: _numeric_column(df, str(columns[ch]), path, ch) for ch in CHANNELS}
    t_raw = _numeric_column(df, str(columns["t"]), path, "t") * time_scale if "t" in columns else None
    t, rate = _time_axis(t_raw, len(df), rate_hz, path)
    G, gu = convert_gyro(np.column_stack([data[c] for c in GYRO_CHANNELS]), gyro_unit, path)
    A, au = convert_accel(np.column_stack([data[c] for c in ACCEL_CHANNELS]), accel_unit, g_local, path)
    samples = _frame(t, G, A)
    return RawRecording(
        samples,
        gu,
        au,
        float(g_local),
        rate,
        path.name,
        {
            "columns": dict(columns),
            "input_units": {"gyro": gyro_unit, "accel": accel_unit},
            "preamble": preamble,
        },
    )


def _frame(t: np.ndarray, G: np.ndarray, A: np.ndarray) -> pd.DataFrame:
    return pd.DataFrame(
        {
            "t": t,
            **{c: G[:, i] for i, c in enumerate(GYRO_CHANNELS)},
            **{c: A[:, i] for i, c in enumerate(ACCEL_CHANNELS)},
        }
    )


IMUCAL_COLUMNS = {"gx": "gyr_x", "gy": "gyr_y", "gz": "gyr_z", "ax": "acc_x", "ay": "acc_y", "az": "acc_z"}


def read_imucal_csv(
    path: Path | str,
    rate_hz: float = IMUCAL_RATE_HZ,
    gyro_unit: str = "deg/s",
    accel_unit: str = "m/s^2",
    g_local: float = IMUCAL_G,
) -> RawRecording:
    """imucal's session CSV (``n_samples, gyr_x..gyr_z, acc_x..acc_z``): gyro deg/s and accel
    m/s^2 by default; m/s^2 is converted to g with g = 9.81 m/s^2, imucal's own value, so that
    the Ferraris result maps back onto imucal's exactly. Row i is sample i (``t = i / rate``)."""
    rec = read_table_recording(path, IMUCAL_COLUMNS, gyro_unit, accel_unit, rate_hz=rate_hz, g_local=g_local)
    return RawRecording(
        rec.samples,
        rec.gyro_unit,
        rec.accel_unit,
        rec.g_local,
        rate_hz,
        rec.source,
        {**rec.metadata, "format": "imucal-csv"},
    )


def read_imutk_pair(
    acc_path: Path | str,
    gyro_path: Path | str,
    gyro_unit: str = "LSB",
    accel_unit: str = "LSB",
    g_local: float = IMUTK_G,
) -> RawRecording:
    """IMU-TK's two whitespace text files (``t x y z`` per line, raw counts): one for the
    accelerometer, one for the gyro, sampled together. The rows must pair up: same count and
    timestamps within half a sample period."""
    acc_path, gyro_path = Path(acc_path), Path(gyro_path)
    acc = _read_imutk_file(acc_path)
    gyr = _read_imutk_file(gyro_path)
    if len(acc) != len(gyr):
        raise _err(E_UNREADABLE_FILE, gyro_path, f"{len(gyr)} rows but {acc_path.name} has {len(acc)}")
    dt = np.median(np.diff(acc[:, 0])) if len(acc) > 1 else 0.0
    mismatch = np.abs(acc[:, 0] - gyr[:, 0])
    if len(acc) > 1 and mismatch.max() > dt / 2:
        i = int(np.argmax(mismatch))
        raise _err(
            E_UNREADABLE_FILE,
            gyro_path,
            f"timestamps differ from {acc_path.name} by {mismatch[i]:.4g} s at row {i}",
        )
    t, rate = _time_axis(acc[:, 0], len(acc), None, acc_path)
    G, gu = convert_gyro(gyr[:, 1:4], gyro_unit, gyro_path)
    A, au = convert_accel(acc[:, 1:4], accel_unit, g_local, acc_path)
    return RawRecording(
        _frame(t, G, A),
        gu,
        au,
        float(g_local),
        rate,
        f"{acc_path.name}+{gyro_path.name}",
        {
            "format": "imu-tk",
            "t0_s": float(acc[0, 0]),
            "input_units": {"gyro": gyro_unit, "accel": accel_unit},
        },
    )


def _read_imutk_file(path: Path) -> np.ndarray:
    df = _read_table(path)
    if df.shape[1] < 4:
        raise _err(
            E_MISSING_COLUMN, path, f"expected 4 whitespace-separated columns t x y z, got {df.shape[1]}"
        )
    return np.column_stack(
        [_numeric_column(df, str(df.columns[i]), path, n) for i, n in enumerate(("t", "x", "y", "z"))]
    )


def read_section_list(path: Path | str) -> dict[str, tuple[int, int]]:
    """Section list of a Ferraris session: imucal's JSON ``{name: {"start": i, "end": j}}``
    or its CSV (``name,start,end`` with the names as first column). Sample indices, end
    exclusive (``data.iloc[start:end]``, as imucal slices)."""
    path = Path(path)
    if not path.exists():
        raise _err(E_MISSING_FILE, path, "no such section list")
    try:
        if path.suffix.lower() == ".json":
            doc = json.loads(path.read_text())
            return {str(k): (int(v["start"]), int(v["end"])) for k, v in doc.items()}
        df = pd.read_csv(path, index_col=0)
        return {str(k): (int(r["start"]), int(r["end"])) for k, r in df.iterrows()}
    except (KeyError, TypeError, ValueError, AttributeError, json.JSONDecodeError) as exc:
        raise _err(E_UNREADABLE_FILE, path, f"not a section list with start/end per section ({exc})") from exc
