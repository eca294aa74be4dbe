"""The results store: what the nightly flow, reruns and reports share, under ``--results``.

Layout, format 2.0 (every Parquet file written to a temp file in the same directory, fsynced,
then ``os.replace``d)::

    tables/<name>/lot=<lot>.parquet   one file per table and lot (lot percent-encoded), for
                                      every table below; a table's directory exists once the
                                      table has been written, even with no rows
    store.json             {"format_version": "2.0"}
    calibrations/<unit>/<YYYYmmddTHHMMSS.ffffffZ>.json   every calibration ever produced
    runs/<run_id>.json     run log (start, end, counts, progress, errors)
    reports/               written by ``reports.*``
    cache/                 derived values kept between runs (outlier thresholds, flag state,
                           report caches), each rebuilt when missing or stale (docs/flows.md)
    .lock                  held (flock) by the run writing the store

Tables: ``sessions`` (one row per session ever seen: status, error, fingerprint, run id),
``parameters`` (lot/unit/rep/model/parameter), ``summary`` (lot/unit/model/parameter over
reps, outlier flags, stale), ``units`` (state: calibrated | stale | failed, why, file),
``residuals`` (per-step residuals of every calibrated session), ``compensation`` (xu2016
Table 3 rows), ``discovery`` (unit and effect found), ``navigation`` (reruns' drift curves).

Why partitions by lot: a rerun of one unit and a nightly run that stores lot by lot read and
rewrite only the lots they touch (the residuals table alone is ~3,500 rows per unit), and the
reports read only the lot they show. ``read(name)`` concatenates the lots in sorted order
(rows sorted by lot, unit, rep, ... as format 1.0 had them in its single file).

Format 1.0 (``<name>.parquet`` at the root, one file per table) is read transparently and
migrated to 2.0 by the first write (callers hold the lock): each flat table is split into
its lot files, then the flat file is removed. A flat file that is present is authoritative
(a migration that died half-way is redone).

Updating a unit replaces only that unit's rows. A unit whose recalibration fails keeps its
last good parameters, summary and calibration files; the ``units`` table and the ``stale`` /
``stale_reason`` columns of ``summary`` say that they are stale and why, and ``sessions``
holds the failures.
"""

from __future__ import annotations

import errno
import fcntl
import json
import os
import socket
import tempfile
import time
from collections.abc import Iterable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from datetime import UTC, datetime, timedelta
from pathlib import Path
from typing import Any
from urllib.parse import quote, unquote

import numpy as np
import pandas as pd
import pyarrow as pa
import pyarrow.compute as pc
import pyarrow.parquet as pq

from calib_core.results import to_jsonable
from schemas.calibration_file import write_json_atomic
from schemas.store_tables import TABLE_SCHEMAS, conform, schema_problem

STORE_FORMAT_VERSION = "2.0"
LEGACY_FORMAT_VERSION = "1.0"  # flat <name>.parquet at the root; read, and migrated on write
TIMESTAMP_FORMAT = "%Y%m%dT%H%M%S.%fZ"

# column order of each table: its declared schema's (schemas/store_tables.py, documented in
# docs/flows.md); extra columns are kept after them
TABLE_COLUMNS: dict[str, list[str]] = {name: schema.names for name, schema in TABLE_SCHEMAS.items()}
TABLES = tuple(TABLE_COLUMNS)
# dtypes of key columns, so that empty tables and concatenations agree
_KEY_DTYPES = {"lot": "string", "unit": "string", "rep": "Int64"}


class StoreLockedError(RuntimeError):
    """Another run holds the results root."""


class StoreError(RuntimeError):
    """The results store cannot be used as it is (a damaged or missing file, a symbolic link
    where the tool writes): one line naming the file and the fix."""


REPAIR_HINT = "run 'mimucal repair --results {root}' to rebuild what can be rebuilt"


class CalibrationNotFound(LookupError):
    """No calibration of the unit matches the request."""


def utc_now() -> datetime:
    return datetime.now(UTC)


def iso(dt: datetime) -> str:
    return dt.astimezone(UTC).isoformat().replace("+00:00", "Z")


def parse_when(text: str) -> datetime:
    """ISO 8601 date or date-time; naive values are UTC."""
    t = text.strip().replace("Z", "+00:00")
    dt = datetime.fromisoformat(t)
    if dt.tzinfo is None:
        dt = dt.replace(tzinfo=UTC)
    return dt.astimezone(UTC)


def _current_umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


_UMASK = _current_umask()


# Rows are sorted by lot and unit, so row groups of this size let a reader that filters one
# unit (the unit report's navigation curves: 60,000 rows per case) skip the rest; pyarrow's
# default (1M rows) made it decode a whole lot (255 ms vs 73 ms CPU, docs/benchmarks.md)
ROW_GROUP_ROWS = 65_536


# schema metadata key of cache/flag_state.parquet holding its JSON document
FLAG_STATE_METADATA_KEY = b"mimucal.flag_state"


# --- atomic writes ------------------------------------------------------------------------------
def write_parquet_atomic(df: pd.DataFrame, path: Path, table_name: str | None = None) -> None:
    """Parquet via a temp file in the same directory, fsync, then ``os.replace``;
    ``table_name``: with that results table's declared schema (schemas.store_tables)."""
    table = pa.Table.from_pandas(df, preserve_index=False)
    if table_name is not None:
        table = conform(table, table_name)
    write_table_atomic(table, path)


def write_table_atomic(table: pa.Table, path: Path) -> None:
    """An Arrow table as :func:`write_parquet_atomic` writes a frame."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    os.close(fd)
    try:
        pq.write_table(
            table, tmp, compression="zstd", row_group_size=ROW_GROUP_ROWS, **_encoding_options(table.schema)
        )
        with open(tmp, "rb") as fh:
            os.fsync(fh.fileno())
        os.chmod(tmp, 0o666 & ~_UMASK)  # mkstemp makes 0600; the store is read by others
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise


# columns whose row-group statistics readers use (filters on lot and unit, sorted keys)
_STATISTICS_COLUMNS = ("lot", "unit", "rep", "model", "parameter", "effect", "case")


def _encoding_options(schema: pa.Schema) -> dict[str, Any]:
    """Dictionary encoding for every column but the floating-point ones, statistics for the
    key columns only. Values are the same either way; what this saves is the writer's time:
    pyarrow's default tries a dictionary for the random floats of the residual tables before
    falling back to plain (it also made those files ~10 % larger), and computes min/max of
    every column (the 50-unit residuals lot, 184,000 rows: 196 ms -> ~100 ms CPU)."""
    dictionary, stats = [], []
    for f in schema:
        if not pa.types.is_floating(f.type):
            dictionary.append(f.name)
        if f.name in _STATISTICS_COLUMNS:
            stats.append(f.name)
    return {"use_dictionary": dictionary, "write_statistics": stats}


def _fsync_dir(path: Path) -> None:
    """Make renames and unlinks in a directory durable."""
    try:
        fd = os.open(path, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


def _read_files(files: list[Path], columns: list[str] | None = None) -> pd.DataFrame:
    """Lot files concatenated in the given order. Arrow promotes types across files (a column
    that is all null in one lot and float in another comes back float), as one file written
    from the whole frame would have them."""
    tables = []
    for f in files:
        cols = None
        if columns is not None:
            names = set(pq.read_schema(f).names)
            cols = [c for c in columns if c in names]
        tables.append(pq.read_table(f, columns=cols))
    if not tables:
        return pd.DataFrame()
    if len(tables) == 1:
        return tables[0].to_pandas()
    return pa.concat_tables(tables, promote_options="permissive").to_pandas()


def _same_frame(a: pd.DataFrame, b: pd.DataFrame) -> bool:
    """Same columns and exactly the same values (NaN equal to NaN). Dtypes may differ where
    the values do not (a column of Python strings built in memory against the string dtype
    it reads back as): rewriting such a lot would store the same thing again."""
    if list(a.columns) != list(b.columns) or len(a) != len(b):
        return False
    a, b = a.reset_index(drop=True), b.reset_index(drop=True)
    if a.equals(b):
        return True
    try:
        pd.testing.assert_frame_equal(a, b, check_dtype=False, check_exact=True)
    except (AssertionError, TypeError, ValueError):
        return False
    return True


def _is_normal(df: pd.DataFrame, name: str) -> bool:
    """Whether :func:`_normalise` would return the same frame (columns in place, key dtypes)."""
    cols = TABLE_COLUMNS[name]
    if list(df.columns[: len(cols)]) != cols:
        return False
    return all(str(df[c].dtype) == dt for c, dt in _KEY_DTYPES.items() if c in df.columns)


def _normalise(df: pd.DataFrame, name: str) -> pd.DataFrame:
    """The table's columns first (missing ones empty), key columns in their dtypes; ``df``
    itself when it is already so (callers never modify the result in place)."""
    if _is_normal(df, name):
        return df
    cols = TABLE_COLUMNS[name]
    df = df.copy()
    declared = TABLE_SCHEMAS[name]
    for c in cols:
        if c not in df.columns:
            # as the declared type reads back when the column is all null (float NaN,
            # pandas' string dtype); the key columns in their dtypes
            t = declared.field(c).type if c in declared.names else pa.null()
            if c in _KEY_DTYPES:
                dtype = _KEY_DTYPES[c]
            elif pa.types.is_floating(t) or pa.types.is_integer(t):
                dtype = "float64"  # an all-null int64 column reads back as float64 NaN
            elif _is_string(t):
                dtype = "str"
            else:
                dtype = "object"
            df[c] = pd.Series([None] * len(df), dtype=dtype)
    for c, dt in _KEY_DTYPES.items():
        if c in df.columns:
            df[c] = df[c].astype(dt)
    extra = [c for c in df.columns if c not in cols]
    return df[cols + extra]


def _is_string(t: pa.DataType) -> bool:
    return pa.types.is_string(t) or pa.types.is_large_string(t)


def _set_columns(df: pd.DataFrame, hit: np.ndarray, values: dict[str, Any]) -> None:
    """Set columns of the rows ``hit`` in place (booleans as the nullable boolean dtype,
    strings in an object column)."""
    for col, v in values.items():
        if col not in df:
            df[col] = None
        if isinstance(v, bool):
            df[col] = df[col].astype("boolean")
        elif isinstance(v, str):
            df[col] = df[col].astype(object)
        df.loc[hit, col] = v


# --- partitions -----------------------------------------------------------------------------------
TABLES_DIR = "tables"
FORMAT_FILE = "store.json"
_LOT_PREFIX = "lot="
# rows whose lot is missing; ``quote`` never produces this name (it has no "lot=" prefix)
_NO_LOT_FILE = "nolot.parquet"
# a table without any row: no row, the declared schema, so that every table directory reads
# as one table (pandas, pyarrow.dataset, DuckDB's ``read_parquet('tables/<name>/*.parquet')``);
# not a partition, and removed once the table has a lot file
EMPTY_FILE = "empty.parquet"


def partition_file_name(lot: Any) -> str:
    """``lot=<lot>.parquet``, the lot percent-encoded (a lot name is a directory name of the
    dataset, but may hold characters a file name should not)."""
    if lot is None or (not isinstance(lot, str) and pd.isna(lot)):
        return _NO_LOT_FILE
    return f"{_LOT_PREFIX}{quote(str(lot), safe='')}.parquet"


def lot_of_partition(file_name: str) -> tuple[bool, str | None]:
    """(is a partition file, its lot) for a file name of a table directory."""
    if file_name == _NO_LOT_FILE:
        return True, None
    if file_name.startswith(_LOT_PREFIX) and file_name.endswith(".parquet"):
        return True, unquote(file_name[len(_LOT_PREFIX) : -len(".parquet")])
    return False, None


def _lot_order(lot: str | None) -> tuple[bool, str]:
    """Sort order of lots: as pandas sorts the lot column (strings, missing last)."""
    return (lot is None, lot or "")


_SORT_KEYS = ("lot", "unit", "rep", "model", "parameter", "effect")


def _sorted(df: pd.DataFrame) -> pd.DataFrame:
    sort = [c for c in _SORT_KEYS if c in df]
    if len(df) and sort:
        df = df.sort_values(sort, kind="stable")
    return df.reset_index(drop=True)


def _split_by_lot(df: pd.DataFrame) -> dict[str | None, pd.DataFrame]:
    """Rows of a normalised frame per lot (None: missing lot), order kept."""
    if not len(df):
        return {}
    lot = df["lot"]
    if not lot.hasnans and (lot.iloc[0] == lot).all():  # one lot (every nightly store, rerun)
        return {str(lot.iloc[0]): df.reset_index(drop=True)}
    codes, lots = pd.factorize(lot.astype(object), use_na_sentinel=True)
    out: dict[str | None, pd.DataFrame] = {}
    for i, lot in enumerate(lots):
        out[str(lot)] = df[codes == i].reset_index(drop=True)
    if (codes < 0).any():
        out[None] = df[codes < 0].reset_index(drop=True)
    return out


def _lot_set(lots: Iterable[Any]) -> set[str | None]:
    """Distinct lots (None: missing); a column of a frame is reduced to its distinct values
    first (it has one value per row)."""
    if isinstance(lots, pd.Series):
        lots = lots.unique()
    return {None if (x is None or (not isinstance(x, str) and pd.isna(x))) else str(x) for x in lots}


# --- the store ------------------------------------------------------------------------------------
@dataclass
class ResultsStore:
    root: Path
    # whether this object's first write has checked every lot file against the declared
    # schemas (see _migrate)
    _schemas_checked: bool = field(default=False, init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        self.root = Path(self.root)

    # paths
    def _check(self, name: str) -> None:
        if name not in TABLE_COLUMNS:
            raise KeyError(f"unknown table {name!r}; tables: {', '.join(TABLES)}")

    @property
    def tables_dir(self) -> Path:
        return self.root / TABLES_DIR

    def table_dir(self, name: str) -> Path:
        """``tables/<name>/``: one Parquet file per lot."""
        self._check(name)
        return self.tables_dir / name

    def partition_path(self, name: str, lot: str | None) -> Path:
        """``tables/<name>/lot=<lot>.parquet``."""
        return self.table_dir(name) / partition_file_name(lot)

    def legacy_path(self, name: str) -> Path:
        """Where format 1.0 kept the whole table (``<name>.parquet`` at the root)."""
        self._check(name)
        return self.root / f"{name}.parquet"

    @property
    def format_path(self) -> Path:
        return self.root / FORMAT_FILE

    @property
    def calibrations_dir(self) -> Path:
        return self.root / "calibrations"

    @property
    def runs_dir(self) -> Path:
        return self.root / "runs"

    @property
    def reports_dir(self) -> Path:
        return self.root / "reports"

    @property
    def lock_path(self) -> Path:
        return self.root / ".lock"

    def format_version(self) -> str | None:
        """``1.0`` while any flat format-1.0 table is present (not yet migrated), ``2.0`` once
        written by this code, None for an empty root."""
        if any(self.legacy_path(n).exists() for n in TABLES):
            return LEGACY_FORMAT_VERSION
        if self.format_path.exists() or self.tables_dir.is_dir():
            return STORE_FORMAT_VERSION
        return None

    def has_table(self, name: str) -> bool:
        """Whether the table was ever written (it may have no rows)."""
        return self.legacy_path(name).exists() or self.table_dir(name).is_dir()

    def exists(self) -> bool:
        return self.has_table("sessions")

    def partitions(self, name: str) -> dict[str | None, Path]:
        """The table's lot files, lot -> path, in lot order (format 2.0 only)."""
        d = self.table_dir(name)
        found = {}
        if d.is_dir():
            for p in d.iterdir():
                ok, lot = lot_of_partition(p.name)
                if ok:
                    found[lot] = p
        return {k: found[k] for k in sorted(found, key=_lot_order)}

    def partition_stats(self, name: str) -> dict[str | None, tuple[int, int, int]] | None:
        """(size, mtime_ns, inode) of each lot file of a table: what a cache derived from a
        lot's rows is checked against (every write replaces the file, so a rewritten lot has
        a new inode). None while the table is a format-1.0 flat file (no per-lot files)."""
        if self.legacy_path(name).exists():
            return None
        out = {}
        for lot, path in self.partitions(name).items():
            try:
                st = path.stat()
            except FileNotFoundError:
                continue
            out[lot] = (st.st_size, st.st_mtime_ns, st.st_ino)
        return out

    def table_lots(self, name: str) -> list[str]:
        """Lots that have rows in the table (from the file names; no data read)."""
        legacy = self.legacy_path(name)
        if legacy.exists():
            try:
                lots = pq.read_table(legacy, columns=["lot"]).column("lot").to_pylist()
            except FileNotFoundError:  # migrated meanwhile
                return self.table_lots(name)
            return sorted({str(x) for x in lots if x is not None})
        return [lot for lot in self.partitions(name) if lot is not None]

    # tables
    def read(
        self, name: str, lots: Iterable[Any] | None = None, columns: list[str] | None = None
    ) -> pd.DataFrame:
        """A table, or the rows of some lots (``lots``; all by default), lots concatenated in
        sorted order; an empty frame with its columns when there is no row. ``columns``
        projects (missing ones come back empty)."""
        self._check(name)
        want = None if lots is None else _lot_set(lots)
        legacy = self.legacy_path(name)
        if legacy.exists():
            try:
                df = self._read_legacy(legacy, want, columns)
            except FileNotFoundError:  # migrated between the check and the read
                return self.read(name, lots, columns)
        else:
            parts = self.partitions(name)
            files = [p for lot, p in parts.items() if want is None or lot in want]
            df = _read_files(files, columns)
        df = _normalise(df, name)
        return df if columns is None else df[list(columns)]

    @staticmethod
    def _read_legacy(path: Path, want: set[str | None] | None, columns: list[str] | None) -> pd.DataFrame:
        cols = None
        if columns is not None:
            names = set(pq.read_schema(path).names)
            cols = [c for c in dict.fromkeys([*columns, "lot"]) if c in names]
        table = pq.read_table(path, columns=cols)
        if want is not None:
            lot = table.column("lot").to_pandas().astype(object)
            lot = lot.where(lot.notna(), None)
            table = table.filter(
                pa.array(lot.isin(want).to_numpy() | (lot.isna().to_numpy() & (None in want)))
            )
        return table.to_pandas()

    def write(
        self,
        name: str,
        df: pd.DataFrame,
        lots: Iterable[Any] | None = None,
        skip_unchanged: bool = False,
        previous: pd.DataFrame | None = None,
    ) -> list[str | None]:
        """Write ``df`` as the table's rows of ``lots`` (default: the whole table, so lots
        absent from ``df`` lose their file). Only the lots' files are rewritten, each
        atomically; a lot left without rows loses its file. ``skip_unchanged``: leave a lot's
        file alone when its rows are equal to what is stored, i.e. to its rows in
        ``previous`` (the table as the caller read it) or else to its file. Returns the lots
        written."""
        self._migrate()
        df = _sorted(_normalise(df, name))
        by_lot = _split_by_lot(df)
        before = None
        if skip_unchanged and previous is not None:
            before = _split_by_lot(_sorted(_normalise(previous, name)))
        current = self.partitions(name)
        if lots is None:
            targets = set(current) | set(by_lot)
        else:
            targets = _lot_set(lots)
            outside = set(by_lot) - targets
            if outside:
                raise ValueError(
                    f"table {name}: rows of lots {sorted(map(str, outside))} given "
                    f"to a write of lots {sorted(map(str, targets))}"
                )
        self.table_dir(name).mkdir(parents=True, exist_ok=True)
        written = []
        for lot in sorted(targets, key=_lot_order):
            part = by_lot.get(lot)
            path = self.partition_path(name, lot)
            if part is None or not len(part):
                if path.exists():
                    path.unlink()
                    written.append(lot)
                continue
            if skip_unchanged and lot in current:
                old = before.get(lot) if before is not None else _normalise(_read_files([current[lot]]), name)
                if old is not None and _same_frame(old, part):
                    continue
            write_parquet_atomic(part, path, name)
            written.append(lot)
        self._keep_readable(name)
        return written

    def _keep_readable(self, name: str) -> None:
        """``tables/<name>/empty.parquet`` while the table has no lot file, none once it has
        one (written after the lot files, so a reader always finds a file with the schema)."""
        empty = self.table_dir(name) / EMPTY_FILE
        if self.partitions(name):
            if empty.exists():
                empty.unlink()
        elif not empty.exists():
            write_parquet_atomic(_normalise(pd.DataFrame(), name), empty, name)

    def replace_units(
        self,
        name: str,
        new_rows: pd.DataFrame | None,
        units: set[tuple[str, str]],
        set_values: dict[tuple[str, str], dict[str, Any]] | None = None,
    ) -> None:
        """Replace every row of the given (lot, unit)s by ``new_rows``; other rows unchanged.
        ``set_values``: columns to set on the kept rows of other units (as
        :meth:`update_rows`), in the same write. Reads and rewrites only the lots of
        ``units``, ``new_rows`` and ``set_values``, each lot file once.

        A lot whose stored rows all belong to ``units`` (a nightly run recalibrating the
        whole lot) is not read beyond its unit column. Otherwise (a rerun) the lot file is
        filtered and merged in Arrow when the new rows have the stored types: the stored rows
        are sorted (every write sorts them), so the new rows, sorted, go in by unit (a stable
        sort on the unit alone) instead of converting and sorting the whole lot in pandas."""
        self._migrate()
        new = None if new_rows is None else _normalise(new_rows, name)
        set_values = set_values or {}
        lots = _lot_set(lot for lot, _ in units) | _lot_set(lot for lot, _ in set_values)
        new_by_lot = _split_by_lot(_sorted(new)) if new is not None else {}
        lots |= set(new_by_lot)
        self.table_dir(name).mkdir(parents=True, exist_ok=True)
        for lot in sorted(lots, key=_lot_order):
            lot_units = {u for lt, u in units if _lot_set([lt]) == {lot}}
            lot_new = new_by_lot.get(lot)
            lot_values = {u: v for (lt, u), v in set_values.items() if _lot_set([lt]) == {lot}}
            if not lot_values and self._merge_lot_arrow(name, lot, lot_units, lot_new):
                continue
            kept = self._rows_kept(name, lot, lot_units)
            if kept is not None and lot_values:
                kept = kept.copy()
                for unit, values in lot_values.items():
                    _set_columns(kept, kept["unit"].astype(object).eq(unit).to_numpy(), values)
            parts = [p for p in (kept, lot_new) if p is not None and len(p)]
            df = (
                pd.concat(parts, ignore_index=True)
                if len(parts) > 1
                else parts[0]
                if parts
                else _normalise(pd.DataFrame(), name)
            )
            self.write(name, df, lots=[lot])

    def _merge_lot_arrow(self, name: str, lot: str | None, units: set[str], new: pd.DataFrame | None) -> bool:
        """The Arrow path of :meth:`replace_units` for one lot; False (nothing done) when it
        does not apply: no stored file, new rows of other units, other column types."""
        path = self.partition_path(name, lot)
        if self.legacy_path(name).exists() or not path.exists():
            return False
        if new is not None and len(new) and not set(new["unit"].astype(object)) <= units:
            return False
        schema = pq.read_schema(path)  # the stored Arrow types, with the pandas metadata
        if schema_problem(schema, name) is not None:
            return False  # a file of an older layout: rewritten whole, with the declared schema
        if new is not None and len(new):
            add = conform(pa.Table.from_pandas(new, preserve_index=False, nthreads=1), name)
            if not add.schema.remove_metadata().equals(schema.remove_metadata()):
                return False
            add = add.replace_schema_metadata(schema.metadata)
        else:
            add = None
        # strings read as dictionaries (decoding them is most of a read), back to the stored
        # type for writing
        old = pq.read_table(path, read_dictionary=[f.name for f in schema if _is_string(f.type)])
        unit = old.column("unit").combine_chunks()
        names = unit.dictionary.to_pylist()
        codes = unit.indices.fill_null(len(names)).to_numpy()
        rank = np.empty(len(names) + 1, dtype=np.int64)  # a missing unit last, as pandas sorts
        rank[np.argsort(np.array(names, dtype=object), kind="stable")] = np.arange(len(names))
        rank[len(names)] = len(names)
        keep = ~np.array([n in units for n in names] + [False])[codes]
        kept = old.filter(pa.array(keep)).cast(schema)
        if add is None:
            if not kept.num_rows:
                return False  # the lot loses its file: write() does that
            write_table_atomic(kept, path)
            return True
        kept_rank = rank[codes[keep]]
        lo, hi = min(add.column("unit").to_pylist()), max(add.column("unit").to_pylist())
        below = np.array([n < lo for n in names] + [False])[codes[keep]]
        between = np.array([lo <= n <= hi for n in names] + [False])[codes[keep]]
        if np.all(np.diff(kept_rank) >= 0) and not between.any():
            # the usual case (one unit rerun): the new rows go in at one place
            at = int(below.sum())
            table = pa.concat_tables([kept.slice(0, at), add, kept.slice(at)])
        else:  # stable sort on the unit alone: stored rows are sorted within their unit
            table = pa.concat_tables([kept, add])
            codes = pc.dictionary_encode(table.column("unit").combine_chunks())
            names = codes.dictionary.to_pylist()
            rank = np.empty(len(names) + 1, dtype=np.int64)
            rank[np.argsort(np.array(names, dtype=object), kind="stable")] = np.arange(len(names))
            rank[len(names)] = len(names)
            idx = codes.indices.fill_null(len(names)).to_numpy()
            table = table.take(np.argsort(rank[idx], kind="stable"))
        write_table_atomic(table, path)
        return True

    def _rows_kept(self, name: str, lot: str | None, units: set[str]) -> pd.DataFrame | None:
        """The stored rows of one lot that are not of ``units`` (None when there is none)."""
        legacy = self.legacy_path(name)
        path = self.partition_path(name, lot)
        if not legacy.exists():
            if not path.exists():
                return None
            if units:
                stored = pq.read_table(path, columns=["unit"]).column("unit")
                if all(u in units for u in stored.unique().to_pylist()):
                    return None  # every stored row is replaced: nothing to read
        old = self.read(name, lots=[lot])
        if units and len(old):
            old = old[~old["unit"].astype(object).isin(units).to_numpy()]
        return old

    def update_rows(self, name: str, units: set[tuple[str, str]], **values: Any) -> None:
        """Set columns of the rows of the given units (e.g. ``stale=True``); rewrites only
        their lots."""
        if not units:
            return
        lots = _lot_set(lot for lot, _ in units)
        df = self.read(name, lots=lots)
        if not len(df):
            return
        keys = pd.MultiIndex.from_frame(df[["lot", "unit"]].astype(object))
        _set_columns(df, keys.isin(list(units)), values)
        self.write(name, df, lots=lots)

    # format 1.0 -> 2.0
    def _migrate(self) -> list[str]:
        """Split every flat format-1.0 table into its lot files, then remove the flat file;
        mark the root as format 2.0. Runs on the first write (under the caller's lock);
        idempotent, and a migration that died half-way is redone from the flat file."""
        migrated = []
        for name in TABLES:
            legacy = self.legacy_path(name)
            if not legacy.exists():
                continue
            df = _sorted(_normalise(pq.read_table(legacy).to_pandas(), name))
            d = self.table_dir(name)
            d.mkdir(parents=True, exist_ok=True)
            by_lot = _split_by_lot(df)
            for lot, path in self.partitions(name).items():  # left by a dead migration
                if lot not in by_lot:
                    path.unlink()
            for lot, part in by_lot.items():
                write_parquet_atomic(part, self.partition_path(name, lot), name)
            self._keep_readable(name)
            _fsync_dir(d)
            legacy.unlink()
            migrated.append(name)
        if not self._schemas_checked:
            self._conform_lot_files()
        if migrated or not self.format_path.exists():
            self.root.mkdir(parents=True, exist_ok=True)
            write_json_atomic(
                self.format_path,
                {
                    "format_version": STORE_FORMAT_VERSION,
                    "layout": "tables/<name>/lot=<lot>.parquet",
                    **(
                        {
                            "migrated_from": LEGACY_FORMAT_VERSION,
                            "migrated_tables": migrated,
                            "migrated_at": iso(utc_now()),
                        }
                        if migrated
                        else {}
                    ),
                },
            )
        return migrated

    def _conform_lot_files(self) -> list[Path]:
        """Rewrite every lot file whose schema is not its table's declared one (stores
        written before the schemas were declared); once per store object, on its first
        write (under the caller's lock). Returns the files rewritten."""
        rewritten = []
        for name in TABLES:
            for lot, path in self.partitions(name).items():
                schema = pq.read_schema(path)
                if schema_problem(schema, name) is not None:
                    table = pq.read_table(path)
                    if name == "summary" and "stderr_of_mean" not in schema.names:
                        table = self._with_stderr_of_mean(table, lot)
                    write_table_atomic(conform(table, name), path)
                    rewritten.append(path)
        self._schemas_checked = True
        return rewritten

    def _with_stderr_of_mean(self, summary: pa.Table, lot: str | None) -> pa.Table:
        """A summary lot file written before the summary stored ``stderr_of_mean``, with it
        computed from the lot's ``parameters`` rows (calib_core.results.stderr_of_mean, as
        ``summarise`` computes it for new rows)."""
        from calib_core.results import stderr_of_mean

        params = self.read("parameters", lots=None if lot is None else [lot])
        df = summary.to_pandas()
        key = ["unit", "model", "parameter"]
        if not len(params) or not len(df) or "stderr" not in params:
            return summary
        wide = params.astype({c: str for c in key}).pivot_table(
            index="rep", columns=key, values="stderr", aggfunc="last", dropna=False
        )
        se = pd.Series(stderr_of_mean(wide.to_numpy(float)), index=wide.columns)
        at = pd.MultiIndex.from_frame(df[key].astype(str))
        values = se.reindex(at).to_numpy(float)
        return summary.append_column("stderr_of_mean", pa.array(values, pa.float64()))

    # fingerprints of the last run: (lot, unit, rep) -> fingerprint
    def fingerprints(self) -> dict[tuple[str, str, int], str]:
        df = self.read("sessions", columns=["lot", "unit", "rep", "fingerprint"])
        return {
            (str(r.lot), str(r.unit), int(r.rep)): str(r.fingerprint)
            for r in df.itertuples()
            if pd.notna(r.rep)
        }

    def lots(self) -> list[str]:
        return self.table_lots("units")

    # calibrations
    def save_calibration(
        self, cal, unit: str, extra: dict[str, Any], when: datetime | None = None, jsonable: bool = False
    ) -> Path:
        """A new ``calibrations/<unit>/<timestamp>.json``; never overwrites an existing one.
        ``jsonable``: ``extra`` is written as :func:`jsonable` would make it (numpy values as
        Python ones, NaN as null, datetimes and paths as text)."""
        from schemas.calibration_file import save_calibration
        from schemas.dataset import check_id

        when = when or utc_now()
        d = self.calibrations_dir / check_id(unit, "unit")  # a file name: never '..' etc.
        d.mkdir(parents=True, exist_ok=True)
        for _ in range(1000):
            path = d / f"{when.astimezone(UTC).strftime(TIMESTAMP_FORMAT)}.json"
            if not path.exists():
                break
            when = when + timedelta(microseconds=1)  # same instant twice: keep both
        if jsonable:
            return save_calibration(cal, path, extra, extra_nonfinite="null", default=_store_default)
        return save_calibration(cal, path, extra)

    def calibration_files(self, unit: str) -> list[tuple[datetime, Path]]:
        d = self.calibrations_dir / unit
        out = []
        if d.is_dir():
            for p in d.glob("*.json"):
                if not p.is_file():  # a directory where a file belongs: repair moves it away
                    continue
                try:
                    ts = datetime.strptime(p.stem, TIMESTAMP_FORMAT).replace(tzinfo=UTC)
                except ValueError:
                    continue
                out.append((ts, p))
        return sorted(out)

    def find_calibration(self, unit: str, at: datetime | None = None, before_after: str = "before") -> Path:
        return find_calibration(self.root, unit, at, before_after)

    # derived values worth keeping between processes
    @property
    def outlier_thresholds_path(self) -> Path:
        return self.root / "cache" / "outlier_thresholds.json"

    def read_outlier_thresholds(self) -> dict | None:
        """The outlier thresholds simulated by earlier runs (the document of a
        ``calib_core.outliers.ThresholdTable``), or None when absent or unreadable: a cache,
        never a source of truth (the values are recomputed when missing)."""
        try:
            return json.loads(self.outlier_thresholds_path.read_text())
        except (OSError, ValueError):
            return None

    def write_outlier_thresholds(self, doc: dict) -> None:
        write_json_atomic(self.outlier_thresholds_path, _jsonable(doc))

    @property
    def flag_state_path(self) -> Path:
        return self.root / "cache" / "flag_state.parquet"

    def read_flag_state(self) -> tuple[pd.DataFrame, dict] | None:
        """The outlier flags' state kept by the last re-flag (flows.nightly): the rows the
        pooled scales come from, and a document (which lot files it describes, the pooled
        scales, the configuration). None when absent or unreadable: a cache, rebuilt by a
        full re-flag."""
        try:
            table = pq.read_table(self.flag_state_path)
            doc = json.loads((table.schema.metadata or {})[FLAG_STATE_METADATA_KEY])
        except (OSError, ValueError, KeyError, pa.ArrowException):
            return None
        return table.to_pandas(), doc

    def write_flag_state(self, rows: pd.DataFrame, doc: dict) -> None:
        table = pa.Table.from_pandas(rows, preserve_index=False)
        meta = {**(table.schema.metadata or {}), FLAG_STATE_METADATA_KEY: json.dumps(doc).encode()}
        write_table_atomic(table.replace_schema_metadata(meta), self.flag_state_path)

    # file digests of the sessions, by their stat (schemas.dataset.DigestCache)
    @property
    def digest_cache_path(self) -> Path:
        return self.root / "cache" / "session_digests.json"

    def read_digest_cache(self) -> dict:
        """A cache: empty when absent or unreadable (the files are hashed again)."""
        try:
            doc = json.loads(self.digest_cache_path.read_text())
        except (OSError, ValueError):
            return {}
        return doc.get("entries", {}) if isinstance(doc, dict) and doc.get("version") == 1 else {}

    def write_digest_cache(self, entries: dict) -> None:
        write_json_atomic(self.digest_cache_path, {"version": 1, "entries": entries})

    # the QA configuration (outlier options and limits) every later run applies
    @property
    def qa_config_path(self) -> Path:
        return self.root / "qa-config.toml"

    def read_qa_config(self) -> str | None:
        """The TOML text set by the last ``--config`` (None: the defaults)."""
        try:
            return self.qa_config_path.read_text()
        except FileNotFoundError:
            return None

    def write_qa_config(self, text: str | None) -> None:
        """Keep ``text`` as the QA configuration of every later run; None clears it."""
        if text is None:
            try:
                self.qa_config_path.unlink()
            except FileNotFoundError:
                pass
            return
        path = self.qa_config_path
        path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
        try:
            with os.fdopen(fd, "w") as fh:
                fh.write(text)
                fh.flush()
                os.fsync(fh.fileno())
            os.chmod(tmp, 0o666 & ~_UMASK)
            os.replace(tmp, path)
        except BaseException:
            if os.path.exists(tmp):
                os.unlink(tmp)
            raise

    # each lot's QA context (reference, thresholds, configuration) as its last re-flag left it
    def qa_lot_path(self, lot: str) -> Path:
        return self.root / "qa" / f"{quote(str(lot), safe='')}.json"

    def write_qa_lot(self, lot: str, doc: dict) -> None:
        write_json_atomic(self.qa_lot_path(lot), _jsonable(doc))

    def read_qa_lot(self, lot: str) -> dict | None:
        try:
            return json.loads(self.qa_lot_path(lot).read_text())
        except (OSError, ValueError):
            return None

    # run logs
    def write_run(self, run_id: str, doc: dict[str, Any]) -> Path:
        path = self.runs_dir / f"{run_id}.json"
        write_json_atomic(path, _jsonable(doc))
        return path

    def read_run(self, run_id: str) -> dict[str, Any]:
        return json.loads((self.runs_dir / f"{run_id}.json").read_text())

    def runs(self) -> list[Path]:
        return sorted(self.runs_dir.glob("*.json")) if self.runs_dir.is_dir() else []

    # lock
    @contextmanager
    def lock(
        self, owner: str, wait: bool = False, timeout: float | None = None, poll_s: float = 0.5
    ) -> Iterator[None]:
        """Hold the results root for one run. ``flock`` is released by the kernel if the
        process dies, so a crashed run never leaves the store locked. A second run is refused
        with :class:`StoreLockedError` naming the holder, or waits (``wait=True``)."""
        self.root.mkdir(parents=True, exist_ok=True)
        try:  # never through a symbolic link: it would truncate the file it points to
            fd = os.open(self.lock_path, os.O_RDWR | os.O_CREAT | os.O_NOFOLLOW, 0o644)
        except OSError as exc:
            if exc.errno == errno.ELOOP:
                raise StoreError(
                    f"{self.lock_path} is a symbolic link; the results folder "
                    f"must hold only the tool's own files: remove it"
                ) from None
            raise
        if not stat_is_regular(fd):
            os.close(fd)
            raise StoreError(f"{self.lock_path} is not a regular file: remove it")
        start = time.monotonic()
        try:
            while True:
                try:
                    fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
                    break
                except OSError as exc:
                    if exc.errno not in (errno.EAGAIN, errno.EACCES, errno.EWOULDBLOCK):
                        raise
                    holder = self.lock_holder() or "another run"
                    if not wait or (timeout is not None and time.monotonic() - start > timeout):
                        raise StoreLockedError(
                            f"results root {self.root} is in use by {holder}; two runs on one "
                            f"results root would corrupt it. Wait for it to finish or pass "
                            f"--wait"
                        ) from None
                    time.sleep(poll_s)
            info = json.dumps(
                {"owner": owner, "pid": os.getpid(), "host": socket.gethostname(), "since": iso(utc_now())}
            )
            os.ftruncate(fd, 0)
            os.pwrite(fd, info.encode(), 0)
            self.remove_stale_temp_files()
            try:
                yield
            finally:
                os.ftruncate(fd, 0)
                fcntl.flock(fd, fcntl.LOCK_UN)
        finally:
            os.close(fd)

    # self-check
    def symlinks(self) -> list[Path]:
        """Symbolic links anywhere under the root (the root itself may be one): the tool
        writes only to its own files and directories, never through a link."""
        found: list[Path] = []
        if not self.root.is_dir():
            return found
        todo = [os.fspath(self.root)]
        while todo:  # scandir's entries know their type: no stat per file (~30,000 files)
            try:
                with os.scandir(todo.pop()) as it:
                    for entry in it:
                        if entry.is_symlink():
                            found.append(Path(entry.path))
                        elif entry.is_dir(follow_symlinks=False):
                            todo.append(entry.path)
            except OSError:
                continue
        return sorted(found)

    def verify(self) -> list[str]:
        """What is wrong with the store, one line per problem (empty: it can be used). Every
        run checks this before writing anything (:meth:`check`): no symbolic link under the
        root, every table file readable (its footer and schema: a truncated or overwritten
        file has neither) with the declared columns castable, every current calibration file
        (``units.calibration_file``) present."""
        problems = []
        hint = REPAIR_HINT.format(root=self.root)
        for link in self.symlinks():
            problems.append(
                f"{link} is a symbolic link; the results folder must hold only "
                f"the tool's own files and directories: replace it by a real "
                f"file/directory or remove it"
            )
        if problems:
            return problems
        units_ok = True
        for name in TABLES:
            empty = self.table_dir(name) / EMPTY_FILE
            files = (
                ([self.legacy_path(name)] if self.legacy_path(name).exists() else [])
                + list(self.partitions(name).values())
                + ([empty] if empty.exists() else [])
            )
            for path in files:
                why = _unreadable(path, name)
                if why:
                    problems.append(f"table {name}: {path} is damaged ({why}); {hint}")
                    units_ok = units_ok and name != "units"
        if units_ok and self.has_table("units"):
            units = self.read("units", columns=["lot", "unit", "state", "calibration_file"])
            for r in units.itertuples():
                f = r.calibration_file
                if not (isinstance(f, str) and f):
                    continue
                if not (self.root / f).is_file() and not (self.root / f).is_dir():
                    problems.append(
                        f"unit {r.lot}/{r.unit}: its current calibration file "
                        f"{self.root / f} is missing; {hint}"
                    )
                    continue
                why = calibration_file_problem(self.root / f)
                if why:
                    problems.append(
                        f"unit {r.lot}/{r.unit}: its current calibration file {self.root / f} {why}; {hint}"
                    )
        problems += [f"{p}; {hint}" for p in self.config_file_problems()]
        return problems

    def config_file_problems(self) -> list[str]:
        """``store.json`` and the stored QA configuration: present files that cannot be used
        (not a regular file, not JSON with a format version, TOML that does not parse)."""
        out = []
        fp = self.format_path
        if os.path.lexists(fp):
            why = None
            if not fp.is_file():
                why = "is not a regular file"
            else:
                try:
                    doc = json.loads(fp.read_bytes()[:65536].decode("utf-8"))
                    if not isinstance(doc, dict) or not isinstance(doc.get("format_version"), str):
                        why = "has no format_version"
                except (OSError, ValueError):
                    why = "is not JSON"
            if why:
                out.append(f"{fp} {why}")
        qp = self.qa_config_path
        if os.path.lexists(qp):
            if not qp.is_file():
                out.append(f"{qp} is not a regular file")
            else:
                from schemas.limits import config_from_toml

                try:
                    config_from_toml(qp.read_bytes()[: 1 << 20].decode("utf-8"), source=str(qp))
                except (OSError, ValueError) as exc:
                    out.append(f"QA configuration {str(exc)[:300]}")
        return out

    @property
    def damaged_dir(self) -> Path:
        return self.root / "damaged"

    def move_damaged(self, path: Path) -> Path:
        """Move a damaged file or directory of the store to ``damaged/<its relative
        path>.<UTC time>`` (kept for a person to look at, out of every run's way)."""
        rel = Path(path).relative_to(self.root)
        dest = self.damaged_dir / rel.parent / f"{rel.name}.{utc_now().strftime(TIMESTAMP_FORMAT)}"
        dest.parent.mkdir(parents=True, exist_ok=True)
        os.replace(path, dest)
        return dest

    def check(self) -> None:
        """:meth:`verify`, raising :class:`StoreError` with the first problem (and how many
        more there are)."""
        problems = self.verify()
        if problems:
            more = f" (and {len(problems) - 1} more problem(s))" if len(problems) > 1 else ""
            raise StoreError(problems[0] + more)

    def ensure_unlocked(self) -> None:
        """Refuse early (before any orchestration starts) when another run holds the root.
        Advisory: the run still takes :meth:`lock`, which is what guarantees exclusion."""
        if not self.lock_path.exists():
            return
        with self.lock("probe"):
            pass

    def remove_stale_temp_files(self) -> list[Path]:
        """Delete the temp files (``.<name>.<random>.tmp``) of writers that died mid-write
        (SIGKILL, power loss: their ``except`` never ran). Only called while holding the
        lock, so no live writer owns them; the files they were replacing are intact."""
        removed = []
        for d in (
            self.root,
            self.runs_dir,
            self.root / "cache",
            self.root / "qa",
            *(self.calibrations_dir.glob("*") if self.calibrations_dir.is_dir() else ()),
            *(self.tables_dir.glob("*") if self.tables_dir.is_dir() else ()),
        ):
            if not d.is_dir():
                continue
            for p in d.glob(".*.tmp"):
                try:
                    p.unlink()
                    removed.append(p)
                except FileNotFoundError:
                    pass
        return removed

    def lock_holder(self) -> str | None:
        try:
            info = json.loads(self.lock_path.read_text() or "{}")
        except (OSError, ValueError):
            return None
        if not info:
            return None
        return (
            f"run {info.get('owner')} (pid {info.get('pid')} on {info.get('host')}, "
            f"since {info.get('since')})"
        )


def calibration_times(results: Path | str, unit: str) -> list[tuple[datetime, datetime, Path, str]]:
    """Every calibration file of ``unit`` as (time, produced, path, source of the time),
    sorted by time then production. The time of a calibration is when its unit was measured:
    ``provenance.acquired_at`` (its sessions' last ``session_start``; source
    ``"session_start"``), else when it was produced (the file name, source
    ``"processing time"``: sessions without ``session_start``, or files of older code)."""
    out = []
    for produced, path in ResultsStore(Path(results)).calibration_files(unit):
        when, source = produced, "processing time"
        try:
            prov = json.loads(path.read_text()).get("provenance") or {}
            if isinstance(prov.get("acquired_at"), str):
                when, source = parse_when(prov["acquired_at"]), "session_start"
        except (OSError, ValueError, AttributeError):
            pass
        out.append((when, produced, path, source))
    return sorted(out, key=lambda x: (x[0], x[1]))


def stat_is_regular(fd: int) -> bool:
    import stat

    return stat.S_ISREG(os.fstat(fd).st_mode)


def calibration_file_problem(path: Path) -> str | None:
    """Why a stored calibration file cannot be one the store wrote (None: it can be): not a
    regular file, or not starting and ending as :func:`schemas.calibration_file.save_calibration`
    writes them. Reads the first and last bytes only (every run checks each unit's current
    file)."""
    from schemas.calibration_file import FORMAT

    path = Path(path)
    if not path.is_file():
        return "is not a regular file"
    try:
        with open(path, "rb") as fh:
            head = fh.read(512)
            size = os.fstat(fh.fileno()).st_size
            fh.seek(max(size - 16, 0))
            tail = fh.read()
    except OSError as exc:
        return f"cannot be read ({exc.strerror or exc})"
    if not head.startswith(b"{") or FORMAT.encode() not in head or not tail.rstrip().endswith(b"}"):
        return "is not a mimucal calibration file (damaged or overwritten)"
    return None


def _unreadable(path: Path, name: str) -> str | None:
    """Why a table file cannot be read with its declared schema (None: it can)."""
    try:
        schema = pq.read_schema(path)
    except (OSError, pa.ArrowException) as exc:
        return f"{type(exc).__name__}: {exc}".splitlines()[0]
    declared = TABLE_SCHEMAS[name]
    for f in declared:
        if f.name in schema.names:
            got = schema.field(f.name).type
            if not (got.equals(f.type) or pa.types.is_null(got) or _castable(got, f.type)):
                return f"column {f.name!r} has type {got}, not castable to {f.type}"
    return None


def _castable(a: pa.DataType, b: pa.DataType) -> bool:
    try:
        pa.array([], type=a).cast(b)
    except (pa.ArrowException, NotImplementedError):
        return False
    return True


def find_calibration(
    results: Path | str, unit: str, at: datetime | None = None, before_after: str = "before"
) -> Path:
    """The calibration file of ``unit`` valid at ``at`` (default: now).

    ``before`` (default): the latest calibration of a measurement at or before ``at``;
    ``after``: the earliest at or after; ``closest``: the nearest either way (imucal's
    ``find_closest_calibration_info_to_date`` with ``before_after=None``). Times are
    acquisition times (:func:`calibration_times`); of several calibrations of one
    measurement (recalibrated with newer code) the last produced is given."""
    if before_after not in ("before", "after", "closest"):
        raise ValueError("before_after must be 'before', 'after' or 'closest'")
    at = at or utc_now()
    if at.tzinfo is None:
        at = at.replace(tzinfo=UTC)
    files = calibration_times(results, unit)
    if not files:
        cal_dir = Path(results) / "calibrations"
        have = sorted(p.name for p in cal_dir.iterdir() if p.is_dir()) if cal_dir.is_dir() else []
        listed = ", ".join(have[:12]) + (f", ... ({len(have)} in all)" if len(have) > 12 else "")
        raise CalibrationNotFound(
            f"no calibration of unit {unit!r} under {cal_dir / unit} "
            f"(units with calibrations: {listed or 'none'})"
        )

    def last_of(when: datetime) -> Path:  # the last produced of one measurement
        return [f for f in files if f[0] == when][-1][2]

    if before_after == "before":
        cands = [f for f in files if f[0] <= at]
        if not cands:
            raise CalibrationNotFound(
                f"unit {unit!r}: no calibration at or before {iso(at)} "
                f"(the first is of {iso(files[0][0])}, {files[0][3]})"
            )
        return last_of(cands[-1][0])
    if before_after == "after":
        cands = [f for f in files if f[0] >= at]
        if not cands:
            raise CalibrationNotFound(
                f"unit {unit!r}: no calibration at or after {iso(at)} "
                f"(the last is of {iso(files[-1][0])}, {files[-1][3]})"
            )
        return last_of(cands[0][0])
    return last_of(min(files, key=lambda f: abs((f[0] - at).total_seconds()))[0])


def _store_default(obj: Any) -> Any:
    if isinstance(obj, datetime):
        return iso(obj)
    if isinstance(obj, Path):
        return str(obj)
    return obj


def _jsonable(obj: Any) -> Any:
    """JSON-safe copy: numpy to Python, non-finite floats to None, datetimes and paths to str."""
    return to_jsonable(obj, _store_default)


jsonable = _jsonable
