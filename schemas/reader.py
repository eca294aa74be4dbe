"""Read one session and validate every rule of the contract.

Only the contract's columns are read (column projection; extra columns are never
decoded). Every check is vectorised (numpy / pyarrow compute), none loops over samples. Units
are converted here, at the boundary: ``rad/s`` -> deg/s, ``m/s^2`` -> g (divided by the
session's ``g_local``); ``LSB`` and ``V`` stay raw.

Order of checks (the first failure is the one reported): files exist -> steps.parquet
readable, columns, types, content -> samples.parquet readable, metadata, columns, types,
content (step ids, time, finite values).

Speed (docs/benchmarks.md): a session is read with two ``ParquetFile.read`` calls with column
projection and no pandas on the sample path. ``steps.parquet`` is the same small table in every
session of a fleet, so its validated form is cached by the SHA-256 of the file's bytes (an
LRU of :data:`STEPS_CACHE_SIZE`; only successful validations are cached, and every caller gets
its own copy); the sample -> step-row index computed for the unknown-step check is handed to
the averaging (``SessionData.step_row``) instead of being searched again.
"""
from __future__ import annotations

import hashlib
import re
import threading
from collections import OrderedDict
from dataclasses import dataclass
from pathlib import Path
from typing import Mapping

import numpy as np
import pandas as pd
import pyarrow as pa
import pyarrow.parquet as pq

from calib_core.steps import SessionKey
from schemas.contract import (
    ACCEL_COLUMNS, ALLOWED_TESTS, ALLOWED_UP_AXES, F_REF_COLUMNS, GYRO_COLUMNS, SAMPLES_FILE,
    SAMPLES_RULES, STEPS_FILE, STEPS_RULES, W_REF_COLUMNS, SessionMeta, check_columns,
    parse_metadata,
)
from schemas.dataset import SessionRef
from schemas.errors import (
    E_BAD_STEP_DEFINITION, E_DUPLICATE_STEP, E_EMPTY_SESSION, E_MISSING_FILE,
    E_NONFINITE_VALUE, E_NONINCREASING_TIME, E_UNKNOWN_STEP, E_UNREADABLE_FILE, E_WRONG_TYPE,
    SessionError,
)

INT32_MIN, INT32_MAX = -(2 ** 31), 2 ** 31 - 1
STEPS_CACHE_SIZE = 16
LOOKUP_MAX_ID = 1 << 20  # step ids in [-1, this): sample -> step row by a lookup table


@dataclass(frozen=True)
class SessionData:
    """A validated session, in mimucal's inside units. Samples are in file order (``t``
    strictly increasing)."""

    key: SessionKey | None
    label: str  # how messages name the session
    steps: pd.DataFrame  # contract columns, validated, in file order
    step: np.ndarray  # (n,) int32 step id of each sample (-1 between steps)
    t: np.ndarray  # (n,) float64 s
    gyro: np.ndarray  # (n, 3) float64, meta.gyro_unit
    accel: np.ndarray  # (n, 3) float64, meta.accel_unit
    temp_c: np.ndarray | None  # (n,) float64 or None when not recorded
    meta: SessionMeta
    # (n,) row of ``steps`` of each sample (-1 between steps); None: the averaging computes it
    step_row: np.ndarray | None = None

    @property
    def sample_rate_hz(self) -> float:
        if self.meta.sample_rate_hz:
            return float(self.meta.sample_rate_hz)
        dt = np.diff(self.t)
        return float(1.0 / np.median(dt)) if len(dt) else float("nan")


# --- files --------------------------------------------------------------------------------
def _open(path: Path, label: str) -> pq.ParquetFile:
    file = path.name
    if not path.exists():
        raise SessionError(E_MISSING_FILE, label, file, f"file is missing ({path})")
    if not path.is_file():
        raise SessionError(E_UNREADABLE_FILE, label, file, f"{path} is not a regular file")
    if path.stat().st_size == 0:
        raise SessionError(E_UNREADABLE_FILE, label, file, "file is empty (0 bytes)")
    try:
        return pq.ParquetFile(path)
    except (pa.ArrowException, OSError, ValueError) as exc:
        raise SessionError(E_UNREADABLE_FILE, label, file,
                           f"not a readable Parquet file (truncated or corrupt?): {exc}") from exc


def _read(pf: pq.ParquetFile, columns: list[str], label: str, file: str) -> pa.Table:
    try:
        return pf.read(columns=columns, use_threads=True)
    except (pa.ArrowException, OSError, ValueError, EOFError) as exc:
        raise SessionError(E_UNREADABLE_FILE, label, file,
                           f"Parquet data cannot be decoded (truncated or corrupt?): {exc}") from exc


# --- steps --------------------------------------------------------------------------------
def _as_table(obj, file: str, label: str) -> pa.Table:
    if isinstance(obj, pa.Table):
        return obj
    if isinstance(obj, pd.DataFrame):
        try:
            return pa.Table.from_pandas(obj, preserve_index=False)
        except (pa.ArrowException, TypeError, ValueError) as exc:
            raise SessionError(E_WRONG_TYPE, label, file, f"table cannot be typed: {exc}") from exc
    raise TypeError(f"expected a pyarrow.Table or pandas.DataFrame, got {type(obj).__name__}")


def _strings(col: pa.ChunkedArray) -> np.ndarray:
    if pa.types.is_dictionary(col.type):
        col = col.cast(col.type.value_type)
    return np.asarray(col.to_numpy(zero_copy_only=False), dtype=object)


def _floats(col: pa.ChunkedArray) -> np.ndarray:
    if pa.types.is_null(col.type):
        return np.full(len(col), np.nan)
    return col.cast(pa.float64()).to_numpy(zero_copy_only=False)


def _int_ids(col: pa.ChunkedArray, label: str, file: str, null_code: str) -> np.ndarray:
    if col.null_count:
        raise SessionError(null_code, label, file,
                           f"{col.null_count} row(s) have a null step id", column="step")
    ids = col.to_numpy(zero_copy_only=False).astype(np.int64, copy=False)
    if len(ids) and (ids.min() < INT32_MIN or ids.max() > INT32_MAX):
        bad = int(ids[(ids < INT32_MIN) | (ids > INT32_MAX)][0])
        raise SessionError(E_WRONG_TYPE, label, file,
                           f"step id {bad} does not fit int32", column="step")
    return ids


def validate_steps(table: pa.Table | pd.DataFrame, label: str,
                   file: str = STEPS_FILE) -> pd.DataFrame:
    """Types and content of steps.parquet -> DataFrame with the contract dtypes (+ duration_s
    when present). Raises SessionError."""
    table = _as_table(table, file, label)
    names = check_columns(table.schema, STEPS_RULES, label, file)
    if table.num_rows == 0:
        raise SessionError(E_EMPTY_SESSION, label, file, "steps table has no rows")
    ids = _int_ids(table.column("step"), label, file, E_BAD_STEP_DEFINITION)
    if (ids == -1).any():
        raise SessionError(E_BAD_STEP_DEFINITION, label, file,
                           "step id -1 is reserved for samples between steps", column="step",
                           step=-1)
    uniq, counts = np.unique(ids, return_counts=True)
    if (counts > 1).any():
        dup = uniq[counts > 1]
        raise SessionError(E_DUPLICATE_STEP, label, file,
                           f"step id {int(dup[0])} appears {int(counts[counts > 1][0])} times "
                           f"({len(dup)} duplicated id(s) in total)", column="step",
                           step=int(dup[0]))
    out = {"step": ids.astype(np.int32)}
    for name, allowed in (("test", ALLOWED_TESTS), ("up_axis", ALLOWED_UP_AXES)):
        values = _strings(table.column(name))
        bad = ~np.isin(values, np.array(allowed, dtype=object))
        if bad.any():
            i = int(np.flatnonzero(bad)[0])
            raise SessionError(E_BAD_STEP_DEFINITION, label, file,
                               f"{name} {values[i]!r} is not one of {', '.join(allowed)} "
                               f"({int(bad.sum())} step(s))", column=name, step=int(ids[i]))
        # built as the pandas string dtype directly (an astype of the frame costs ~3 ms)
        out[name] = pd.array(values.astype(str).astype(object), dtype="string")
    for name in ("rate_dps", "angle_deg") + W_REF_COLUMNS + F_REF_COLUMNS + ("settle_s",):
        values = _floats(table.column(name))
        bad = np.isinf(values) if name == "angle_deg" else ~np.isfinite(values)
        if bad.any():
            i = int(np.flatnonzero(bad)[0])
            raise SessionError(E_BAD_STEP_DEFINITION, label, file,
                               f"{name} is {values[i]} (must be a finite number; "
                               f"{int(bad.sum())} step(s))", column=name, step=int(ids[i]))
        out[name] = values
    if (out["settle_s"] < 0).any():
        i = int(np.flatnonzero(out["settle_s"] < 0)[0])
        raise SessionError(E_BAD_STEP_DEFINITION, label, file,
                           f"settle_s is {out['settle_s'][i]} (must be >= 0)", column="settle_s",
                           step=int(ids[i]))
    if "duration_s" in table.schema.names and "duration_s" not in names:
        col = table.column("duration_s")
        if pa.types.is_floating(col.type) or pa.types.is_integer(col.type):
            out["duration_s"] = _floats(col)
    return pd.DataFrame(out)


_steps_cache: OrderedDict[bytes, pd.DataFrame] = OrderedDict()
_steps_lock = threading.Lock()  # the nightly flow reads sessions from a thread pool


def read_steps(path: Path, label: str) -> pd.DataFrame:
    _open(path, label)  # existence, type, size and Parquet checks, each with its own error
    try:
        raw = path.read_bytes()
    except OSError as exc:
        raise SessionError(E_UNREADABLE_FILE, label, path.name, f"cannot read {path}: {exc}") from exc
    digest = hashlib.sha256(raw).digest()
    with _steps_lock:
        cached = _steps_cache.get(digest)
        if cached is not None:
            _steps_cache.move_to_end(digest)
            return cached.copy()
    try:
        pf = pq.ParquetFile(pa.BufferReader(raw))
    except (pa.ArrowException, OSError, ValueError) as exc:  # changed since _open looked at it
        raise SessionError(E_UNREADABLE_FILE, label, path.name,
                           f"not a readable Parquet file (truncated or corrupt?): {exc}") from exc
    names = check_columns(pf.schema_arrow, STEPS_RULES, label, path.name)
    if "duration_s" in pf.schema_arrow.names:
        names = names + ["duration_s"]
    df = validate_steps(_read(pf, names, label, path.name), label, path.name)
    with _steps_lock:
        _steps_cache[digest] = df.copy()
        while len(_steps_cache) > STEPS_CACHE_SIZE:
            _steps_cache.popitem(last=False)
    return df


# --- samples ------------------------------------------------------------------------------
def _first_bad(bad: np.ndarray, step: np.ndarray | None) -> tuple[int, int | None]:
    i = int(np.flatnonzero(bad)[0])
    return i, (None if step is None else int(step[i]))


def validate_samples(table: pa.Table | pd.DataFrame, steps: pd.DataFrame, meta: SessionMeta,
                     label: str, file: str = SAMPLES_FILE,
                     key: SessionKey | None = None) -> SessionData:
    """Types and content of samples.parquet, unit conversion -> :class:`SessionData`."""
    table = _as_table(table, file, label)
    check_columns(table.schema, SAMPLES_RULES, label, file)
    n = table.num_rows
    if n == 0:
        raise SessionError(E_EMPTY_SESSION, label, file, "samples table has no rows")
    step = _int_ids(table.column("step"), label, file, E_UNKNOWN_STEP)
    step_row = _step_rows(step, steps["step"].to_numpy(np.int64))
    unknown_rows = step_row == -2
    if unknown_rows.any():
        unknown = np.unique(step[unknown_rows])
        n_rows = int(unknown_rows.sum())
        raise SessionError(E_UNKNOWN_STEP, label, file,
                           f"step id {int(unknown[0])} is not in steps.parquet ({len(unknown)} "
                           f"unknown id(s), {n_rows} sample(s))", column="step",
                           step=int(unknown[0]))
    step = step.astype(np.int32)

    t_col = table.column("t")
    t = _floats(t_col)
    bad = ~np.isfinite(t)
    if bad.any():
        i, s = _first_bad(bad, step)
        what = "null" if t_col.null_count else f"{t[i]}"
        raise SessionError(E_NONFINITE_VALUE, label, file,
                           f"time is {what} at row {i} ({int(bad.sum())} row(s))", column="t",
                           step=s)
    nonincreasing = np.diff(t) <= 0
    if nonincreasing.any():
        i = int(np.flatnonzero(nonincreasing)[0]) + 1
        raise SessionError(E_NONINCREASING_TIME, label, file,
                           f"t is not strictly increasing: row {i} has t={float(t[i])!r} s after "
                           f"t={float(t[i - 1])!r} s ({int(nonincreasing.sum())} such row(s))",
                           column="t", step=int(step[i]))

    def sensor(names: tuple[str, ...], scale: float) -> np.ndarray:
        out = np.empty((n, 3), order="F")  # column-major: per-channel work is contiguous
        for j, name in enumerate(names):
            col = table.column(name)
            values = _floats(col)
            bad = ~np.isfinite(values)
            if bad.any():
                i, s = _first_bad(bad, step)
                kinds = []
                if col.null_count:
                    kinds.append(f"{col.null_count} null")
                n_nan = int(np.isnan(values).sum()) - col.null_count
                if n_nan:
                    kinds.append(f"{n_nan} NaN")
                if np.isinf(values).any():
                    kinds.append(f"{int(np.isinf(values).sum())} infinite")
                raise SessionError(E_NONFINITE_VALUE, label, file,
                                   f"non-finite sensor values ({', '.join(kinds)}), first at "
                                   f"row {i} (t={t[i]:.6g} s)", column=name, step=s)
            out[:, j] = values
        if scale != 1.0:
            out *= scale
        return out

    gyro = sensor(GYRO_COLUMNS, meta.gyro_scale)
    accel = sensor(ACCEL_COLUMNS, meta.accel_scale)
    temp = None
    if "temp_c" in table.schema.names:
        temp = _floats(table.column("temp_c"))  # NaN / null = not recorded for that sample
        if np.isinf(temp).any():
            i, s = _first_bad(np.isinf(temp), step)
            raise SessionError(E_NONFINITE_VALUE, label, file,
                               f"temperature is infinite at row {i}", column="temp_c", step=s)
    return SessionData(key=key, label=label, steps=steps, step=step, t=t, gyro=gyro,
                       accel=accel, temp_c=temp, meta=meta, step_row=step_row)


def _step_rows(step: np.ndarray, ids: np.ndarray) -> np.ndarray:
    """Row of ``ids`` (unique step ids) for every sample's step id: -1 for the between-steps
    id -1, -2 for an id not in ``ids``. A lookup table when the ids are small (the usual
    0..N), a binary search otherwise; no sort of the samples either way."""
    n_ids = len(ids)
    lo = int(min(ids.min(initial=0), step.min(initial=0)))
    hi = int(max(ids.max(initial=0), step.max(initial=0)))
    rows = np.arange(n_ids, dtype=np.int32)
    if lo >= -1 and hi < LOOKUP_MAX_ID:
        lut = np.full(hi + 2, -2, dtype=np.int32)  # position 0 is id -1
        lut[0] = -1
        lut[ids + 1] = rows
        return lut[step + 1]
    order = np.argsort(ids, kind="stable")
    sorted_ids = ids[order]
    pos = np.clip(np.searchsorted(sorted_ids, step), 0, max(n_ids - 1, 0))
    found = sorted_ids[pos] == step
    out = np.where(found, order[pos], -2).astype(np.int32)
    out[step == -1] = -1
    return out


def read_session(ref: SessionRef) -> SessionData:
    """Read and validate one session directory. Raises :class:`SessionError`."""
    label = str(ref.key)
    missing = [p for p in (ref.steps_path, ref.samples_path) if not p.exists()]
    if missing:
        names = " and ".join(p.name for p in missing)
        raise SessionError(E_MISSING_FILE, label, missing[0].name,
                           f"{names} missing in {ref.path}")
    steps = read_steps(ref.steps_path, label)
    pf = _open(ref.samples_path, label)
    file = ref.samples_path.name
    meta = parse_metadata(pf.schema_arrow.metadata, label, file)
    names = check_columns(pf.schema_arrow, SAMPLES_RULES, label, file)
    table = _read(pf, names, label, file)
    return validate_samples(table, steps, meta, label, file, key=ref.key)


def session_from_tables(key: SessionKey | str, steps: pa.Table | pd.DataFrame,
                        samples: pa.Table | pd.DataFrame,
                        metadata: Mapping | None = None) -> SessionData:
    """Validate in-memory tables exactly as :func:`read_session` validates files. When
    ``metadata`` is None the samples table's schema metadata is used."""
    label = str(key)
    steps_df = validate_steps(steps, label, STEPS_FILE)
    if metadata is None:
        metadata = samples.schema.metadata if isinstance(samples, pa.Table) else {}
    meta = parse_metadata(metadata, label, SAMPLES_FILE)
    return validate_samples(samples, steps_df, meta, label, SAMPLES_FILE, key=parse_key(key))


def parse_key(key: SessionKey | str) -> SessionKey | None:
    """``"lot=L1/unit=U1/rep=2"`` -> SessionKey; None when a plain label does not parse."""
    if isinstance(key, SessionKey):
        return key
    m = _KEY_PATTERN.match(str(key))
    return SessionKey(m["lot"], m["unit"], int(m["rep"])) if m else None


_KEY_PATTERN = re.compile(r"^lot=(?P<lot>[A-Za-z0-9_.-]+)/unit=(?P<unit>[A-Za-z0-9_.-]+)"
                          r"/rep=(?P<rep>[1-9][0-9]*)$")
