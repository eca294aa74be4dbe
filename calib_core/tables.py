"""Light tables for per-session results: numpy columns, one pandas DataFrame per unit.

A pandas DataFrame costs about 1 ms to build (more than the fits of a session), and a string
column costs ~0.3 us per element to convert from numpy's fixed-width unicode to pandas'
Arrow-backed ``str``. Per-session residual and compensation tables are therefore kept as
:class:`ColumnTable` (plain numpy columns, scalars for constant columns, and
:class:`CodedStrings` for repetitive string columns); a unit's sessions are concatenated and
turned into ONE DataFrame, equal (columns, order, dtypes, values) to concatenating
per-session DataFrames built the plain way.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache
from typing import Any

import numpy as np


@dataclass(frozen=True)
class CodedStrings:
    """A string column as its distinct values and one integer code per row."""

    categories: np.ndarray  # (k,) str, distinct
    codes: np.ndarray  # (n,) int, index into categories

    @classmethod
    def of(cls, values: np.ndarray) -> CodedStrings:
        """Codes of a string array (np.unique: fine for a session's ~100 steps)."""
        cats, codes = np.unique(np.asarray(values), return_inverse=True)
        return cls(cats, codes.ravel())

    @classmethod
    def constant(cls, value: str, n: int) -> CodedStrings:
        return cls(np.array([value]), np.zeros(n, dtype=np.intp))

    def __len__(self) -> int:
        return len(self.codes)

    def repeat(self, k: int) -> CodedStrings:
        """Each row k times (np.repeat)."""
        return CodedStrings(self.categories, np.repeat(self.codes, k))

    def strings(self) -> np.ndarray:
        return self.categories[self.codes]

    @staticmethod
    def concat(parts: list[CodedStrings]) -> CodedStrings:
        cats = parts[0].categories
        if all(np.array_equal(p.categories, cats) for p in parts[1:]):
            return CodedStrings(cats, np.concatenate([p.codes for p in parts]))
        cats = np.unique(np.concatenate([p.categories for p in parts]))
        return CodedStrings(
            cats, np.concatenate([np.searchsorted(cats, p.categories)[p.codes] for p in parts])
        )

    def to_pandas(self):
        """The column as pandas would build it from the strings (its default string dtype),
        without converting row by row: the distinct values as an Arrow array, taken by code."""
        arrow = _arrow_string_type()
        if arrow is None:  # pandas without Arrow-backed strings: let pandas convert
            return self.strings()
        import pyarrow as pa

        array_type, dt, typ = arrow
        return array_type(pa.array(self.categories.tolist(), type=typ).take(self.codes), dtype=dt)


@lru_cache(maxsize=1)
def _arrow_string_type():
    """(pandas dtype, Arrow type) pandas gives a numpy string column, or None when that is
    not an Arrow-backed string column (then the plain conversion is used)."""
    import pandas as pd

    try:
        import pyarrow as pa
    except ImportError:  # pragma: no cover - pyarrow is a dependency
        return None
    ref = pd.Series(np.array(["a", "bc"]))
    if not isinstance(ref.dtype, pd.StringDtype) or ref.dtype.storage != "pyarrow":
        return None
    array_type = type(ref.array)
    typ = pa.array(ref.array).type
    try:
        probe = array_type(pa.array(["a", "bc"], type=typ), dtype=ref.dtype)
    except TypeError:  # pragma: no cover - a pandas whose constructor differs
        return None
    if not (pd.Series(probe).equals(ref) and probe.dtype == ref.dtype):  # pragma: no cover
        return None
    return array_type, ref.dtype, typ


def _is_str_scalar(v: Any) -> bool:
    return isinstance(v, str)


class ColumnTable:
    """Rows of a table as named columns: an (n,) numpy array, a :class:`CodedStrings`, or one
    scalar shared by every row."""

    __slots__ = ("columns", "n_rows")

    def __init__(self, columns: dict[str, Any], n_rows: int):
        self.columns = dict(columns)
        self.n_rows = int(n_rows)
        for name, v in self.columns.items():
            if isinstance(v, (np.ndarray, CodedStrings)) and len(v) != self.n_rows:
                raise ValueError(f"column {name!r} has {len(v)} rows, expected {self.n_rows}")

    def __len__(self) -> int:
        return self.n_rows

    def __repr__(self) -> str:
        return f"ColumnTable({self.n_rows} rows: {', '.join(self.columns)})"

    def column(self, name: str) -> np.ndarray:
        """One column as an (n,) numpy array."""
        v = self.columns[name]
        if isinstance(v, CodedStrings):
            return v.strings()
        return v if isinstance(v, np.ndarray) else np.full(self.n_rows, v)

    def with_leading(self, name: str, value: Any) -> ColumnTable:
        """A copy with a constant column ``name`` inserted first (DataFrame.insert(0, ...))."""
        return ColumnTable({name: value, **self.columns}, self.n_rows)

    @staticmethod
    def concat(tables: list[ColumnTable]) -> ColumnTable:
        """Rows of every table in order (pd.concat(..., ignore_index=True)); the tables must
        have the same columns in the same order. A column that is the same scalar in every
        table stays a scalar; string columns stay coded."""
        if not tables:
            raise ValueError("no table to concatenate")
        names = list(tables[0].columns)
        for t in tables[1:]:
            if list(t.columns) != names:
                raise ValueError(f"columns differ: {names} vs {list(t.columns)}")
        out: dict[str, Any] = {}
        for name in names:
            vals = [t.columns[name] for t in tables]
            first = vals[0]
            if not isinstance(first, (np.ndarray, CodedStrings)) and all(
                type(v) is type(first) and v == first for v in vals[1:]
            ):
                out[name] = first
            elif all(isinstance(v, CodedStrings) or _is_str_scalar(v) for v in vals):
                out[name] = CodedStrings.concat(
                    [
                        v if isinstance(v, CodedStrings) else CodedStrings.constant(v, t.n_rows)
                        for v, t in zip(vals, tables)
                    ]
                )
            else:
                out[name] = np.concatenate([t.column(name) for t in tables])
        return ColumnTable(out, sum(t.n_rows for t in tables))

    def to_frame(self):
        """The pandas DataFrame (default RangeIndex)."""
        import pandas as pd

        if self.n_rows == 0:
            return pd.DataFrame(columns=list(self.columns))
        data = {}
        for name, v in self.columns.items():
            if _is_str_scalar(v):  # pandas repeats a scalar string slowly: code it
                v = CodedStrings.constant(v, self.n_rows)
            data[name] = v.to_pandas() if isinstance(v, CodedStrings) else v
        return pd.DataFrame(data, columns=list(self.columns))
