"""Read one session and validate every rule of the contract.

Only the contract's columns are read (column projection; extra columns are never
decoded). Every check is vectorised (numpy / pyarrow compute), none loops over samples. Units
are converted here, at the boundary: ``rad/s`` -> deg/s, ``m/s^2`` -> g (divided by the
session's ``g_local``); ``LSB`` and ``V`` stay raw.

Order of checks (the first failure is the one reported): files exist -> steps.parquet
readable, columns, types, content -> samples.parquet readable, metadata, columns, types,
content (step ids, time, finite values).

Speed (docs/benchmarks.md): each file is read once, whole, into memory (by the caller that
fingerprints the same bytes, :func:`schemas.dataset.read_session_files`, or here; a samples
file over :data:`schemas.dataset.MAX_HELD_BYTES` is read by its path instead), and parsed
from that buffer with one ``ParquetFile.read`` with column projection and no pandas on the
sample path. ``steps.parquet`` is the same small table in every session of a fleet, so its
validated form (the DataFrame and its columns as read-only numpy arrays, :class:`StepColumns`)
is cached by the content digest of the file's bytes, a hit taken only when the bytes are
equal (an LRU of :data:`STEPS_CACHE_SIZE`; only successful validations are cached; a hit skips
the Parquet parsing, and every caller gets its own copy-on-write copy of the frame). The six sensor columns
are converted once into one ``(6, n)`` float64 array (``SessionData.channels``; ``gyro`` and
``accel`` are views of it) and checked for finiteness by summing them over the session's
pieces (:mod:`schemas.segments`: the kept segments of each step and the samples between
them), the sums the averaging starts from (``SessionData.piece_sums``); the per-column search
that builds the error message runs only when that check fails. Sample times are checked in
one comparison pass (strictly increasing between finite ends), the exact searches only when
it fails. The sample -> step-row index and the runs computed for the unknown-step check are
handed to the averaging (``SessionData.step_row``, ``SessionData.segments``).
"""

from __future__ import annotations

import errno
import math
import os
import re
import stat
import threading
from collections import OrderedDict
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd
import pyarrow as pa
import pyarrow.parquet as pq

from calib_core.steps import SessionKey
from schemas.contract import (
    ALLOWED_TESTS,
    ALLOWED_UP_AXES,
    F_REF_COLUMNS,
    SAMPLES_FILE,
    SAMPLES_RULES,
    SENSOR_COLUMNS,
    STEP_FLOAT_COLUMNS,
    STEPS_FILE,
    STEPS_RULES,
    W_REF_COLUMNS,
    SessionMeta,
    check_columns,
    parse_metadata,
)
from schemas.dataset import SessionFiles, SessionRef
from schemas.errors import (
    E_BAD_STEP_DEFINITION,
    E_CHECKSUM,
    E_DUPLICATE_STEP,
    E_EMPTY_SESSION,
    E_MISSING_FILE,
    E_NONFINITE_VALUE,
    E_NONINCREASING_TIME,
    E_STEP_NOT_CONTIGUOUS,
    E_UNKNOWN_STEP,
    E_UNREADABLE_FILE,
    E_WRONG_TYPE,
    SessionError,
)
from schemas.hive import bytes_digest, read_regular_file
from schemas.segments import Segments, kept_segments

INT32_MIN, INT32_MAX = -(2**31), 2**31 - 1
STEPS_CACHE_SIZE = 16
LOOKUP_MAX_ID = 1 << 20  # step ids in [-1, this): sample -> step row by a lookup table


@dataclass(frozen=True)
class StepColumns:
    """The validated steps table as numpy arrays, in file order: what the averaging needs,
    taken out of pandas once per distinct steps file (each pandas column access costs tens of
    microseconds, the string columns milliseconds). Arrays are read-only: one instance is
    shared by every session with the same steps.parquet."""

    step: np.ndarray  # (k,) int64
    test: np.ndarray  # (k,) str
    up_axis: np.ndarray  # (k,) str
    rate_dps: np.ndarray  # (k,) float64
    angle_deg: np.ndarray  # (k,) float64
    settle_s: np.ndarray  # (k,) float64
    w_ref: np.ndarray  # (k, 3) float64
    f_ref: np.ndarray  # (k, 3) float64
    heading_deg: np.ndarray | None = None  # (k,) float64, the optional column (None: absent)

    @classmethod
    def from_frame(cls, steps: pd.DataFrame) -> StepColumns:
        """From a validated steps DataFrame (the contract columns)."""

        def read_only(a: np.ndarray) -> np.ndarray:
            a = np.array(a)  # own copy: never a view of the caller's frame
            a.setflags(write=False)
            return a

        floats = {c: steps[c].to_numpy(float) for c in STEP_FLOAT_COLUMNS}
        return cls(
            step=read_only(steps["step"].to_numpy(np.int64)),
            test=read_only(steps["test"].to_numpy(str)),
            up_axis=read_only(steps["up_axis"].to_numpy(str)),
            rate_dps=read_only(floats["rate_dps"]),
            angle_deg=read_only(floats["angle_deg"]),
            settle_s=read_only(floats["settle_s"]),
            w_ref=read_only(np.column_stack([floats[c] for c in W_REF_COLUMNS])),
            f_ref=read_only(np.column_stack([floats[c] for c in F_REF_COLUMNS])),
            heading_deg=(
                read_only(steps["heading_deg"].to_numpy(float)) if "heading_deg" in steps.columns else None
            ),
        )


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
    # Derived forms handed from the reader to the averaging (None: the averaging derives them
    # from the fields above). Replacing ``steps``, ``step``, ``gyro`` or ``accel`` with
    # dataclasses.replace must replace these too (or set them to None).
    # (n,) row of ``steps`` of each sample (-1 between steps)
    step_row: np.ndarray | None = None
    # ``steps`` as numpy arrays
    step_columns: StepColumns | None = None
    # (6, n) float64, rows gx gy gz ax ay az; ``gyro`` is ``channels[:3].T``, ``accel``
    # ``channels[3:].T`` (the averaging checks that they still are)
    channels: np.ndarray | None = None
    # the runs and kept segments of the samples (from ``step``, ``t`` and ``steps``' settle_s;
    # used with ``step_row``)
    segments: Segments | None = None
    # (6, P) ``channels`` summed over ``segments.pieces`` (all finite; None: the averaging sums)
    piece_sums: np.ndarray | None = None

    @property
    def sample_rate_hz(self) -> float:
        if self.meta.sample_rate_hz:
            return float(self.meta.sample_rate_hz)
        dt = np.diff(self.t)
        return float(1.0 / np.median(dt)) if len(dt) else float("nan")


# --- files --------------------------------------------------------------------------------
def _stat(path: Path) -> os.stat_result | None:
    """``path``'s stat, None where :meth:`Path.exists` says False (the errors it ignores: no
    such file, not a directory, a symlink loop, a bad path), other OS errors raised as it
    raises them: one system call answers exists, is_file and the size."""
    try:
        return path.stat()
    except OSError as exc:
        if exc.errno in _STAT_MISSING_ERRNOS:
            return None
        raise
    except ValueError:  # an embedded NUL
        return None


_STAT_MISSING_ERRNOS = (errno.ENOENT, errno.ENOTDIR, errno.EBADF, errno.ELOOP)


def _open(path: Path, label: str, st: os.stat_result | None = None) -> pq.ParquetFile:
    """Checks of existence, type and size, each with its own error, then the Parquet footer.
    ``st``: ``path``'s :func:`_stat` when the caller has it (else taken here)."""
    file = path.name
    if st is None:
        st = _stat(path)
    if st is None:
        raise SessionError(E_MISSING_FILE, label, file, f"file is missing ({path})")
    if not stat.S_ISREG(st.st_mode):
        raise SessionError(E_UNREADABLE_FILE, label, file, f"{path} is not a regular file")
    if st.st_size == 0:
        raise SessionError(E_UNREADABLE_FILE, label, file, "file is empty (0 bytes)")
    try:
        # page CRCs are verified where the writer stored them (schemas.writer does)
        return pq.ParquetFile(path, page_checksum_verification=True)
    except (pa.ArrowException, OSError, ValueError) as exc:
        raise SessionError(
            E_UNREADABLE_FILE, label, file, f"not a readable Parquet file (truncated or corrupt?): {exc}"
        ) from exc


def _open_buffer(raw: bytes, label: str, file: str) -> pq.ParquetFile:
    """The Parquet footer of a file's bytes already read (:func:`_open`'s last check)."""
    try:
        return pq.ParquetFile(pa.BufferReader(raw), page_checksum_verification=True)
    except (pa.ArrowException, OSError, ValueError) as exc:
        raise SessionError(
            E_UNREADABLE_FILE, label, file, f"not a readable Parquet file (truncated or corrupt?): {exc}"
        ) from exc


# Arrow's own threads for decoding one file's columns: a lone read of a session is faster in
# wall time with them, for a little more CPU (thread hand-offs).
# Worker processes that already keep every core busy read in their own thread
# (flows.compute_pool turns them off: on 2 busy cores the hand-offs are pure cost).
_arrow_threads = True


def use_arrow_threads(enabled: bool) -> None:
    """Whether session reads decode their columns on Arrow's thread pool (default: yes)."""
    global _arrow_threads
    _arrow_threads = bool(enabled)


def _read(pf: pq.ParquetFile, columns: list[str], label: str, file: str) -> pa.Table:
    try:
        return pf.read(columns=columns, use_threads=_arrow_threads)
    except (pa.ArrowException, OSError, ValueError, EOFError) as exc:
        if "crc" in str(exc).lower() or "checksum" in str(exc).lower():
            raise SessionError(
                E_CHECKSUM,
                label,
                file,
                f"damaged bytes: a data page's checksum does not match its content ({exc})",
            ) from exc
        raise SessionError(
            E_UNREADABLE_FILE, label, file, f"Parquet data cannot be decoded (truncated or corrupt?): {exc}"
        ) from exc


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
    """float64 values, nulls as NaN (a float64 column without a cast: a no-op that costs a
    compute call)."""
    if pa.types.is_null(col.type):
        return np.full(len(col), np.nan)
    if not pa.types.is_float64(col.type):
        col = col.cast(pa.float64())
    return col.to_numpy(zero_copy_only=False)


def _int_ids(col: pa.ChunkedArray, label: str, file: str, null_code: str) -> np.ndarray:
    """Step ids as int32 (zero-copy, possibly read-only) when the column is int32, else int64
    after a range check."""
    if col.null_count:
        raise SessionError(
            null_code, label, file, f"{col.null_count} row(s) have a null step id", column="step"
        )
    ids = col.to_numpy(zero_copy_only=False)
    if ids.dtype == np.int32:  # the contract's type: in range by construction, no copy
        return ids
    ids = ids.astype(np.int64, copy=False)
    if len(ids) and (ids.min() < INT32_MIN or ids.max() > INT32_MAX):
        bad = int(ids[(ids < INT32_MIN) | (ids > INT32_MAX)][0])
        raise SessionError(E_WRONG_TYPE, label, file, f"step id {bad} does not fit int32", column="step")
    return ids


def validate_steps(table: pa.Table | pd.DataFrame, label: str, file: str = STEPS_FILE) -> pd.DataFrame:
    """Types and content of steps.parquet -> DataFrame with the contract dtypes (+ duration_s
    when present). Raises SessionError."""
    return _validate_steps_frame(_as_table(table, file, label), label, file)


def _validated_steps(
    table: pa.Table | pd.DataFrame, label: str, file: str = STEPS_FILE
) -> tuple[pd.DataFrame, StepColumns]:
    df = validate_steps(table, label, file)
    return df, StepColumns.from_frame(df)


def _validate_steps_frame(table: pa.Table, label: str, file: str) -> pd.DataFrame:
    names = check_columns(table.schema, STEPS_RULES, label, file)
    if table.num_rows == 0:
        raise SessionError(E_EMPTY_SESSION, label, file, "steps table has no rows")
    ids = _int_ids(table.column("step"), label, file, E_BAD_STEP_DEFINITION)
    if (ids == -1).any():
        raise SessionError(
            E_BAD_STEP_DEFINITION,
            label,
            file,
            "step id -1 is reserved for samples between steps",
            column="step",
            step=-1,
        )
    uniq, counts = np.unique(ids, return_counts=True)
    if (counts > 1).any():
        dup = uniq[counts > 1]
        raise SessionError(
            E_DUPLICATE_STEP,
            label,
            file,
            f"step id {int(dup[0])} appears {int(counts[counts > 1][0])} times "
            f"({len(dup)} duplicated id(s) in total)",
            column="step",
            step=int(dup[0]),
        )
    out = {"step": ids.astype(np.int32)}
    for name, allowed in (("test", ALLOWED_TESTS), ("up_axis", ALLOWED_UP_AXES)):
        try:
            values = _strings(table.column(name))
        except (pa.ArrowException, UnicodeDecodeError) as exc:  # bytes that are not UTF-8
            raise SessionError(
                E_UNREADABLE_FILE,
                label,
                file,
                f"{name} strings cannot be decoded (corrupt file?): {exc}",
                column=name,
            ) from exc
        bad = ~np.isin(values, np.array(allowed, dtype=object))
        if bad.any():
            i = int(np.flatnonzero(bad)[0])
            raise SessionError(
                E_BAD_STEP_DEFINITION,
                label,
                file,
                f"{name} {values[i]!r} is not one of {', '.join(allowed)} ({int(bad.sum())} step(s))",
                column=name,
                step=int(ids[i]),
            )
        # built as the pandas string dtype directly (an astype of the whole frame costs more)
        out[name] = pd.array(values.astype(str).astype(object), dtype="string")
    for name in ("rate_dps", "angle_deg") + W_REF_COLUMNS + F_REF_COLUMNS + ("settle_s",):
        values = _floats(table.column(name))
        bad = np.isinf(values) if name == "angle_deg" else ~np.isfinite(values)
        if bad.any():
            i = int(np.flatnonzero(bad)[0])
            raise SessionError(
                E_BAD_STEP_DEFINITION,
                label,
                file,
                f"{name} is {values[i]} (must be a finite number; {int(bad.sum())} step(s))",
                column=name,
                step=int(ids[i]),
            )
        out[name] = values
    if (out["settle_s"] < 0).any():
        i = int(np.flatnonzero(out["settle_s"] < 0)[0])
        raise SessionError(
            E_BAD_STEP_DEFINITION,
            label,
            file,
            f"settle_s is {out['settle_s'][i]} (must be >= 0)",
            column="settle_s",
            step=int(ids[i]),
        )
    if "duration_s" in table.schema.names and "duration_s" not in names:
        col = table.column("duration_s")
        if pa.types.is_floating(col.type) or pa.types.is_integer(col.type):
            out["duration_s"] = _floats(col)
    if "heading_deg" in table.schema.names and "heading_deg" not in names:
        col = table.column("heading_deg")
        if not (pa.types.is_floating(col.type) or pa.types.is_integer(col.type)):
            raise SessionError(
                E_BAD_STEP_DEFINITION,
                label,
                file,
                f"heading_deg has type {col.type} (must be a number of degrees)",
                column="heading_deg",
            )
        values = _floats(col)
        bad = ~np.isfinite(values)
        if bad.any():
            i = int(np.flatnonzero(bad)[0])
            raise SessionError(
                E_BAD_STEP_DEFINITION,
                label,
                file,
                f"heading_deg is {values[i]} (must be a finite number; {int(bad.sum())} step(s))",
                column="heading_deg",
                step=int(ids[i]),
            )
        out["heading_deg"] = values
    return pd.DataFrame(out)


# validated steps by the content digest of the file's bytes; each entry keeps those bytes and
# a hit is taken only when they are the file's (a digest is no proof of equal content)
_steps_cache: OrderedDict[str, tuple[bytes, pd.DataFrame, StepColumns]] = OrderedDict()
_steps_lock = threading.Lock()  # the nightly flow reads sessions from a thread pool


def read_steps(path: Path, label: str) -> pd.DataFrame:
    """Read and validate steps.parquet -> DataFrame (the caller's own deep copy)."""
    return _read_steps_cached(path, label)[0].copy()


def _read_steps_cached(path: Path, label: str, raw: bytes | None = None) -> tuple[pd.DataFrame, StepColumns]:
    """(the cached frame, its columns). The frame is shared: copy it before handing it out.
    ``raw``: the file's bytes when the caller read them (else read here)."""
    file = path.name
    if raw is None:
        try:
            st = path.stat()
        except OSError:
            st = None
        # a regular non-empty file is read once; anything else takes _open's checks, each
        # with its own error
        if st is not None and stat.S_ISREG(st.st_mode) and st.st_size > 0:
            try:
                raw = read_regular_file(str(path))[0] or None
            except OSError:
                raw = None
    if raw is not None:
        digest = bytes_digest(raw)
        with _steps_lock:
            cached = _steps_cache.get(digest)
            if cached is not None and cached[0] == raw:
                _steps_cache.move_to_end(digest)
                return cached[1], cached[2]
    else:
        _open(path, label)  # existence, type, size and Parquet checks, each with its own error
        try:
            raw = path.read_bytes()
        except OSError as exc:
            raise SessionError(E_UNREADABLE_FILE, label, file, f"cannot read {path}: {exc}") from exc
        digest = bytes_digest(raw)
    pf = _open_buffer(raw, label, file)
    schema = pf.schema_arrow
    names = check_columns(schema, STEPS_RULES, label, file)
    names = names + [c for c in ("duration_s", "heading_deg") if c in schema.names]
    entry = _validated_steps(_read(pf, names, label, file), label, file)
    with _steps_lock:
        _steps_cache[digest] = (raw, *entry)
        while len(_steps_cache) > STEPS_CACHE_SIZE:
            _steps_cache.popitem(last=False)
    return entry


# --- samples ------------------------------------------------------------------------------
def _first_bad(bad: np.ndarray, step: np.ndarray | None) -> tuple[int, int | None]:
    i = int(np.flatnonzero(bad)[0])
    return i, (None if step is None else int(step[i]))


def validate_samples(
    table: pa.Table | pd.DataFrame,
    steps: pd.DataFrame,
    meta: SessionMeta,
    label: str,
    file: str = SAMPLES_FILE,
    key: SessionKey | None = None,
    step_columns: StepColumns | None = None,
) -> SessionData:
    """Types and content of samples.parquet, unit conversion -> :class:`SessionData`.
    ``step_columns``: ``steps`` as numpy arrays when the caller has them (else derived)."""
    return _validate_samples(table, steps, meta, label, file, key, step_columns)


def _validate_samples(
    table: pa.Table | pd.DataFrame,
    steps: pd.DataFrame,
    meta: SessionMeta,
    label: str,
    file: str,
    key: SessionKey | None,
    step_columns: StepColumns | None,
    columns_checked: bool = False,
) -> SessionData:
    """:func:`validate_samples`; ``columns_checked``: the table was read with the projection
    that :func:`check_columns` returned for its file's schema (same columns, same types)."""
    table = _as_table(table, file, label)
    if not columns_checked:
        check_columns(table.schema, SAMPLES_RULES, label, file)
    n = table.num_rows
    if n == 0:
        raise SessionError(E_EMPTY_SESSION, label, file, "samples table has no rows")
    if step_columns is None:
        step_columns = StepColumns.from_frame(steps)
    step = _int_ids(table.column("step"), label, file, E_UNKNOWN_STEP)
    # the samples of a step come in runs: look the ids up once per run, not per sample
    run_start, run_len = _runs(step)
    run_row = _step_rows(step[run_start], step_columns.step)
    unknown_runs = run_row == -2
    if unknown_runs.any():
        unknown = np.unique(step[run_start[unknown_runs]])
        n_rows = int(run_len[unknown_runs].sum())
        raise SessionError(
            E_UNKNOWN_STEP,
            label,
            file,
            f"step id {int(unknown[0])} is not in steps.parquet ({len(unknown)} "
            f"unknown id(s), {n_rows} sample(s))",
            column="step",
            step=int(unknown[0]),
        )
    _check_one_run_per_step(step, run_start, label, file, run_row)
    step = np.array(step, dtype=np.int32)  # own, writable copy (the Arrow buffer is read-only)
    step_row = np.repeat(run_row, run_len)

    t_col = table.column("t")
    t = _floats(t_col)
    # strictly increasing between finite ends: every t is finite (a NaN compares False), so
    # one comparison pass answers both checks; the checks below name the first failure
    increasing = t[1:] > t[:-1]
    if not (np.isfinite(t[0]) and np.isfinite(t[-1]) and increasing.all()):
        _check_times(t, t_col, step, label, file)
    cols = step_columns
    segments = kept_segments(t, run_start, run_start + run_len, run_row, cols.settle_s, len(cols.step))

    # one (6, n) array, one row per channel (each conversion from float32 one contiguous
    # copy); gyro / accel are (n, 3) column-major views of it. The channels are then summed
    # over the pieces of the session (schemas.segments: the kept segments and the samples
    # between them, every sample in one piece) in one reduceat: the averaging's sums, and the
    # finiteness check, as a NaN or infinity makes its piece's sum non-finite (no boolean
    # array); a non-finite sum of finite values (overflow) is told apart by the exact search.
    # Invalid operations are not reported: a signalling NaN in a float32 file stays a NaN.
    channels = pool_empty((len(SENSOR_COLUMNS), n))
    with np.errstate(over="ignore", invalid="ignore"):
        for j, name in enumerate(SENSOR_COLUMNS):
            channels[j] = table.column(name).to_numpy()  # nulls become NaN
        piece_sums = np.add.reduceat(channels, segments.pieces, axis=1)
        finite = bool(np.isfinite(piece_sums).all())
    if not finite:
        _raise_nonfinite_sensor(table, channels, step, t, label, file)
        piece_sums = None  # finite values whose sum overflows: the averaging sums them itself
    if meta.gyro_scale != 1.0:  # after the check, as file values are what the message names
        channels[:3] *= meta.gyro_scale
    if meta.accel_scale != 1.0:
        channels[3:] *= meta.accel_scale
    if piece_sums is not None and (meta.gyro_scale != 1.0 or meta.accel_scale != 1.0):
        with np.errstate(over="ignore", invalid="ignore"):
            piece_sums = np.add.reduceat(channels, segments.pieces, axis=1)
        if not np.isfinite(piece_sums).all():
            piece_sums = None
    temp = None
    if table.schema.get_field_index("temp_c") >= 0:
        temp = _floats(table.column("temp_c"))  # NaN / null = not recorded for that sample
        if np.isinf(temp).any():
            i, s = _first_bad(np.isinf(temp), step)
            raise SessionError(
                E_NONFINITE_VALUE, label, file, f"temperature is infinite at row {i}", column="temp_c", step=s
            )
    return SessionData(
        key=key,
        label=label,
        steps=steps,
        step=step,
        t=t,
        gyro=channels[:3].T,
        accel=channels[3:].T,
        temp_c=temp,
        meta=meta,
        step_row=step_row,
        step_columns=step_columns,
        channels=channels,
        segments=segments,
        piece_sums=piece_sums,
    )


def _check_times(t: np.ndarray, t_col: pa.ChunkedArray, step: np.ndarray, label: str, file: str) -> None:
    """The error for sample times that are not finite or not strictly increasing."""
    bad = ~np.isfinite(t)
    if bad.any():
        i, s = _first_bad(bad, step)
        what = "null" if t_col.null_count else f"{t[i]}"
        raise SessionError(
            E_NONFINITE_VALUE,
            label,
            file,
            f"time is {what} at row {i} ({int(bad.sum())} row(s))",
            column="t",
            step=s,
        )
    # for finite t, t[i+1] - t[i] <= 0 exactly when t[i+1] <= t[i] (no float temporary)
    nonincreasing = t[1:] <= t[:-1]
    if nonincreasing.any():
        i = int(np.flatnonzero(nonincreasing)[0]) + 1
        raise SessionError(
            E_NONINCREASING_TIME,
            label,
            file,
            f"t is not strictly increasing: row {i} has t={float(t[i])!r} s after "
            f"t={float(t[i - 1])!r} s ({int(nonincreasing.sum())} such row(s))",
            column="t",
            step=int(step[i]),
        )


def _check_one_run_per_step(
    step: np.ndarray, run_start: np.ndarray, label: str, file: str, run_row: np.ndarray | None = None
) -> None:
    """E_STEP_NOT_CONTIGUOUS when a step's samples are not one run in time: its id reappears
    after another step's samples (samples of no step, id -1, between two parts of a step do
    not count as another step). ``run_row``: each run's steps-table row (-1 between steps),
    when known: a session whose steps each have one run passes without a sort."""
    if run_row is not None:
        rows = run_row[run_row >= 0]
        if len(rows) < 2 or np.bincount(rows).max() == 1:
            return
    ids = step[run_start]
    keep = ids != -1
    ids, starts = ids[keep], run_start[keep]
    if len(ids) < 2:
        return
    new_run = np.concatenate(([True], ids[1:] != ids[:-1]))  # runs split only by -1 joined
    ids, starts = ids[new_run], starts[new_run]
    _, first = np.unique(ids, return_index=True)
    if len(first) == len(ids):
        return
    again = np.ones(len(ids), bool)
    again[first] = False
    k = int(np.flatnonzero(again)[0])
    sid = int(ids[k])
    n_ids = len(ids) - len(first)
    raise SessionError(
        E_STEP_NOT_CONTIGUOUS,
        label,
        file,
        f"the samples of step {sid} are not one run in time: its id reappears "
        f"at row {int(starts[k])} after another step's samples ({n_ids} "
        f"reappearance(s) in all)",
        column="step",
        step=sid,
    )


def _raise_nonfinite_sensor(
    table: pa.Table, channels: np.ndarray, step: np.ndarray, t: np.ndarray, label: str, file: str
) -> None:
    """The error for the first sensor column (gx .. az order) with a non-finite value."""
    for j, name in enumerate(SENSOR_COLUMNS):
        values = channels[j]
        bad = ~np.isfinite(values)
        if not bad.any():
            continue
        col = table.column(name)
        i, s = _first_bad(bad, step)
        kinds = []
        if col.null_count:
            kinds.append(f"{col.null_count} null")
        n_nan = int(np.isnan(values).sum()) - col.null_count
        if n_nan:
            kinds.append(f"{n_nan} NaN")
        if np.isinf(values).any():
            kinds.append(f"{int(np.isinf(values).sum())} infinite")
        raise SessionError(
            E_NONFINITE_VALUE,
            label,
            file,
            f"non-finite sensor values ({', '.join(kinds)}), first at row {i} (t={t[i]:.6g} s)",
            column=name,
            step=s,
        )
    # every value finite, the sum overflowed: nothing to report


def pool_empty(shape: tuple[int, ...]) -> np.ndarray:
    """An uninitialised float64 array in Arrow's memory pool (mimalloc) instead of glibc's
    malloc: glibc hands the ~1.7 MB arrays of a session back to the kernel when they are
    freed and page-faults them in again for the next session (~850 minor faults, 1-3 ms of
    system CPU per session, measured); the pool keeps freed pages for reuse."""
    size = math.prod(shape) * 8
    return np.frombuffer(pa.allocate_buffer(size), np.float64).reshape(shape)


def _runs(values: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Start and length of each run of equal ``values`` (non-empty)."""
    start = np.flatnonzero(values[1:] != values[:-1]) + 1
    start = np.concatenate(([0], start))
    length = np.empty(len(start), np.intp)
    np.subtract(start[1:], start[:-1], out=length[:-1])
    length[-1] = len(values) - start[-1]
    return start, length


def _step_rows(step: np.ndarray, ids: np.ndarray) -> np.ndarray:
    """Row of ``ids`` (unique step ids) for every sample's step id: -1 for the between-steps
    id -1, -2 for an id not in ``ids``. A lookup table when the ids are small (the usual
    0..N), a binary search otherwise; no sort of the samples either way."""
    n_ids = len(ids)
    lo = int(min(ids.min(initial=0), step.min(initial=0)))
    hi = int(max(ids.max(initial=0), step.max(initial=0)))
    rows = np.arange(n_ids, dtype=np.int32)
    if lo >= -1 and hi < LOOKUP_MAX_ID:
        # positions 0..hi are ids; the last position (hi + 1, not an id) is where numpy's
        # index -1 lands: the between-steps id
        lut = np.full(hi + 2, -2, dtype=np.int32)
        lut[-1] = -1
        lut[ids] = rows
        return lut[step]
    order = np.argsort(ids, kind="stable")
    sorted_ids = ids[order]
    pos = np.clip(np.searchsorted(sorted_ids, step), 0, max(n_ids - 1, 0))
    found = sorted_ids[pos] == step
    out = np.where(found, order[pos], -2).astype(np.int32)
    out[step == -1] = -1
    return out


def read_session(ref: SessionRef, files: SessionFiles | None = None) -> SessionData:
    """Read and validate one session directory. Raises :class:`SessionError`. ``files``: the
    session's files as read once for its fingerprint (:func:`schemas.dataset.read_session_files`):
    their bytes are parsed, not the files read again; a file whose bytes it does not hold
    (missing, empty, not regular, unreadable) is looked at by its path, which says why."""
    label = str(ref.key)
    samples_path = ref.samples_path
    steps_raw = files.steps if files is not None else None
    samples_raw = files.samples if files is not None else None
    steps_there = steps_raw is not None or ref.steps_path.exists()
    samples_stat = None if samples_raw is not None else _stat(samples_path)  # exists, and _open's checks
    missing = [
        p
        for p, there in (
            (ref.steps_path, steps_there),
            (samples_path, samples_raw is not None or samples_stat is not None),
        )
        if not there
    ]
    if missing:
        names = " and ".join(p.name for p in missing)
        raise SessionError(E_MISSING_FILE, label, missing[0].name, f"{names} missing in {ref.path}")
    steps, step_columns = _read_steps_cached(ref.steps_path, label, steps_raw)
    file = samples_path.name
    if samples_raw is not None:
        pf = _open_buffer(samples_raw, label, file)
    else:
        pf = _open(samples_path, label, samples_stat)
    schema = pf.schema_arrow  # built anew by every access: taken once
    meta = parse_metadata(schema.metadata, label, file)
    names = check_columns(schema, SAMPLES_RULES, label, file)
    table = _read(pf, names, label, file)
    # the frame is shared with the cache: a shallow copy is the caller's own under pandas'
    # copy-on-write (writing to it copies), at no cost; the table's columns are the
    # projection of the schema just checked (not checked again)
    return _validate_samples(
        table, steps.copy(deep=False), meta, label, file, ref.key, step_columns, columns_checked=True
    )


def session_from_tables(
    key: SessionKey | str,
    steps: pa.Table | pd.DataFrame,
    samples: pa.Table | pd.DataFrame,
    metadata: Mapping | None = None,
) -> SessionData:
    """Validate in-memory tables exactly as :func:`read_session` validates files. When
    ``metadata`` is None the samples table's schema metadata is used."""
    label = str(key)
    steps_df, step_columns = _validated_steps(steps, label, STEPS_FILE)
    if metadata is None:
        metadata = samples.schema.metadata if isinstance(samples, pa.Table) else {}
    meta = parse_metadata(metadata, label, SAMPLES_FILE)
    return validate_samples(
        samples, steps_df, meta, label, SAMPLES_FILE, key=parse_key(key), step_columns=step_columns
    )


def parse_key(key: SessionKey | str) -> SessionKey | None:
    """``"lot=L1/unit=U1/rep=2"`` -> SessionKey; None when a plain label does not parse."""
    if isinstance(key, SessionKey):
        return key
    m = _KEY_PATTERN.fullmatch(str(key))
    return SessionKey(m["lot"], m["unit"], int(m["rep"])) if m else None


_KEY_PATTERN = re.compile(
    r"^lot=(?P<lot>[A-Za-z0-9_.-]+)/unit=(?P<unit>[A-Za-z0-9_.-]+)"
    r"/rep=(?P<rep>[1-9][0-9]*)$"
)
