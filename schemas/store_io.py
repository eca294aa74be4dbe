"""The results store's file I/O: atomic Parquet writes (temp file in the same directory,
fsync, ``os.replace``), the encoding the store writes with, lot files read back as one frame,
and the store's time stamps and JSON conversion."""

from __future__ import annotations

import os
import tempfile
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import pandas as pd
import pyarrow as pa
import pyarrow.parquet as pq

from calib_core.results import to_jsonable
from schemas.store_tables import conform

TIMESTAMP_FORMAT = "%Y%m%dT%H%M%S.%fZ"

# Rows are sorted by lot and unit, so row groups of this size let a reader that filters one
# unit (the unit report's navigation curves: 60,000 rows per case) skip the rest; pyarrow's
# default (1M rows) made it decode a whole lot (255 ms vs 73 ms CPU, docs/benchmarks.md)
ROW_GROUP_ROWS = 65_536

# columns whose row-group statistics readers use (filters on lot and unit, sorted keys)
_STATISTICS_COLUMNS = ("lot", "unit", "rep", "model", "parameter", "effect", "case")


class StoreError(RuntimeError):
    """The results store cannot be used as it is (a damaged or missing file, a symbolic link
    where the tool writes, a format this code does not know): one line naming the file and
    the fix."""


REPAIR_HINT = "run 'mimucal repair --results {root}' to rebuild what can be rebuilt"


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


UMASK = _current_umask()


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
        os.chmod(tmp, 0o666 & ~UMASK)  # mkstemp makes 0600; the store is read by others
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise


def write_text_atomic(path: Path, text: str) -> None:
    """A text file via a temp file in the same directory, fsync, then ``os.replace``."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "w") as fh:
            fh.write(text)
            fh.flush()
            os.fsync(fh.fileno())
        os.chmod(tmp, 0o666 & ~UMASK)
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise


def _encoding_options(schema: pa.Schema) -> dict[str, Any]:
    """Dictionary encoding for every column but the floating-point ones, statistics for the
    key columns only. Values are the same either way; what this saves is the writer's time:
    pyarrow's default tries a dictionary for the random floats of the residual tables before
    falling back to plain (it also made those files larger), and computes min/max of every
    column (docs/benchmarks.md has the figures)."""
    dictionary, stats = [], []
    for f in schema:
        if not pa.types.is_floating(f.type):
            dictionary.append(f.name)
        if f.name in _STATISTICS_COLUMNS:
            stats.append(f.name)
    return {"use_dictionary": dictionary, "write_statistics": stats}


def fsync_dir(path: Path) -> None:
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


def read_files(files: list[Path], columns: list[str] | None = None) -> pd.DataFrame:
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


def store_default(obj: Any) -> Any:
    if isinstance(obj, datetime):
        return iso(obj)
    if isinstance(obj, Path):
        return str(obj)
    return obj


def jsonable(obj: Any) -> Any:
    """JSON-safe copy: numpy to Python, non-finite floats to None, datetimes and paths to str."""
    return to_jsonable(obj, store_default)
