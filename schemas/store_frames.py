"""The results tables as frames and lot files: each table's columns and key dtypes, a frame
normalised to them, rows split by lot and sorted as the store keeps them, and the names of
the lot files (``tables/<name>/lot=<lot>.parquet``)."""

from __future__ import annotations

from collections.abc import Iterable
from typing import Any
from urllib.parse import quote, unquote

import numpy as np
import pandas as pd
import pyarrow as pa

from schemas.store_tables import TABLE_SCHEMAS

# column order of each table: its declared schema's (schemas/store_tables.py, documented in
# docs/flows.md); extra columns are kept after them
TABLE_COLUMNS: dict[str, list[str]] = {name: schema.names for name, schema in TABLE_SCHEMAS.items()}
TABLES = tuple(TABLE_COLUMNS)
# dtypes of key columns, so that empty tables and concatenations agree
_KEY_DTYPES = {"lot": "string", "unit": "string", "rep": "Int64"}


def same_frame(a: pd.DataFrame, b: pd.DataFrame) -> bool:
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


def is_normal(df: pd.DataFrame, name: str) -> bool:
    """Whether :func:`normalise` would return the same frame (columns in place, key dtypes)."""
    cols = TABLE_COLUMNS[name]
    if list(df.columns[: len(cols)]) != cols:
        return False
    return all(str(df[c].dtype) == dt for c, dt in _KEY_DTYPES.items() if c in df.columns)


def normalise(df: pd.DataFrame, name: str) -> pd.DataFrame:
    """The table's columns first (missing ones empty), key columns in their dtypes; ``df``
    itself when it is already so (callers never modify the result in place)."""
    if is_normal(df, name):
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
            elif is_string(t):
                dtype = "str"
            else:
                dtype = "object"
            df[c] = pd.Series([None] * len(df), dtype=dtype)
    for c, dt in _KEY_DTYPES.items():
        if c in df.columns:
            df[c] = df[c].astype(dt)
    extra = [c for c in df.columns if c not in cols]
    return df[cols + extra]


def is_string(t: pa.DataType) -> bool:
    return pa.types.is_string(t) or pa.types.is_large_string(t)


def set_columns(df: pd.DataFrame, hit: np.ndarray, values: dict[str, Any]) -> None:
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


def lot_order(lot: str | None) -> tuple[bool, str]:
    """Sort order of lots: as pandas sorts the lot column (strings, missing last)."""
    return (lot is None, lot or "")


SORT_KEYS = ("lot", "unit", "rep", "model", "parameter", "effect")


def sorted_rows(df: pd.DataFrame) -> pd.DataFrame:
    sort = [c for c in SORT_KEYS if c in df]
    if len(df) and sort:
        df = df.sort_values(sort, kind="stable")
    return df.reset_index(drop=True)


def split_by_lot(df: pd.DataFrame) -> dict[str | None, pd.DataFrame]:
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


def lot_set(lots: Iterable[Any]) -> set[str | None]:
    """Distinct lots (None: missing); a column of a frame is reduced to its distinct values
    first (it has one value per row)."""
    if isinstance(lots, pd.Series):
        lots = lots.unique()
    return {None if (x is None or (not isinstance(x, str) and pd.isna(x))) else str(x) for x in lots}


# --- the store ------------------------------------------------------------------------------------
