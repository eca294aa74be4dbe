"""The results tables on disk: one Parquet file per table and lot
(``tables/<name>/lot=<lot>.parquet``), read as one frame, written lot by lot, a unit's rows
replaced without rewriting the other lots. Part of :class:`schemas.results_store.ResultsStore`
(``self.root``; the format-1.0 flat files through :mod:`schemas.store_legacy`)."""

from __future__ import annotations

from collections.abc import Iterable
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
import pyarrow as pa
import pyarrow.compute as pc
import pyarrow.parquet as pq

from schemas import store_io
from schemas.store_frames import (
    EMPTY_FILE,
    TABLE_COLUMNS,
    TABLES,
    TABLES_DIR,
    is_string,
    lot_of_partition,
    lot_order,
    lot_set,
    normalise,
    partition_file_name,
    same_frame,
    set_columns,
    sorted_rows,
    split_by_lot,
)
from schemas.store_io import read_files
from schemas.store_tables import conform, schema_problem


class LotTables:
    """The tables of the store rooted at ``self.root``."""

    root: Path

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
        return {k: found[k] for k in sorted(found, key=lot_order)}

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
        self.check_format()
        want = None if lots is None else lot_set(lots)
        legacy = self.legacy_path(name)
        if legacy.exists():
            try:
                df = self._read_legacy(legacy, want, columns)
            except FileNotFoundError:  # migrated between the check and the read
                return self.read(name, lots, columns)
        else:
            parts = self.partitions(name)
            files = [p for lot, p in parts.items() if want is None or lot in want]
            df = read_files(files, columns)
        df = normalise(df, name)
        return df if columns is None else df[list(columns)]

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
        df = sorted_rows(normalise(df, name))
        by_lot = split_by_lot(df)
        before = None
        if skip_unchanged and previous is not None:
            before = split_by_lot(sorted_rows(normalise(previous, name)))
        current = self.partitions(name)
        if lots is None:
            targets = set(current) | set(by_lot)
        else:
            targets = lot_set(lots)
            outside = set(by_lot) - targets
            if outside:
                raise ValueError(
                    f"table {name}: rows of lots {sorted(map(str, outside))} given "
                    f"to a write of lots {sorted(map(str, targets))}"
                )
        self.table_dir(name).mkdir(parents=True, exist_ok=True)
        written = []
        for lot in sorted(targets, key=lot_order):
            part = by_lot.get(lot)
            path = self.partition_path(name, lot)
            if part is None or not len(part):
                if path.exists():
                    path.unlink()
                    written.append(lot)
                continue
            if skip_unchanged and lot in current:
                old = before.get(lot) if before is not None else normalise(read_files([current[lot]]), name)
                if old is not None and same_frame(old, part):
                    continue
            store_io.write_parquet_atomic(part, path, name)
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
            store_io.write_parquet_atomic(normalise(pd.DataFrame(), name), empty, name)

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
        new = None if new_rows is None else normalise(new_rows, name)
        set_values = set_values or {}
        lots = lot_set(lot for lot, _ in units) | lot_set(lot for lot, _ in set_values)
        new_by_lot = split_by_lot(sorted_rows(new)) if new is not None else {}
        lots |= set(new_by_lot)
        self.table_dir(name).mkdir(parents=True, exist_ok=True)
        for lot in sorted(lots, key=lot_order):
            lot_units = {u for lt, u in units if lot_set([lt]) == {lot}}
            lot_new = new_by_lot.get(lot)
            lot_values = {u: v for (lt, u), v in set_values.items() if lot_set([lt]) == {lot}}
            if not lot_values and self._merge_lot_arrow(name, lot, lot_units, lot_new):
                continue
            kept = self._rows_kept(name, lot, lot_units)
            if kept is not None and lot_values:
                kept = kept.copy()
                for unit, values in lot_values.items():
                    set_columns(kept, kept["unit"].astype(object).eq(unit).to_numpy(), values)
            parts = [p for p in (kept, lot_new) if p is not None and len(p)]
            df = (
                pd.concat(parts, ignore_index=True)
                if len(parts) > 1
                else parts[0]
                if parts
                else normalise(pd.DataFrame(), name)
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
        old = pq.read_table(path, read_dictionary=[f.name for f in schema if is_string(f.type)])
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
            store_io.write_table_atomic(kept, path)
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
        store_io.write_table_atomic(table, path)
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
        lots = lot_set(lot for lot, _ in units)
        df = self.read(name, lots=lots)
        if not len(df):
            return
        keys = pd.MultiIndex.from_frame(df[["lot", "unit"]].astype(object))
        set_columns(df, keys.isin(list(units)), values)
        self.write(name, df, lots=lots)

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
