"""Store formats other than this code's: the format-1.0 layout (one flat ``<name>.parquet``
per table at the root), read transparently and migrated to 2.0 by the first write; lot files
written before the tables' schemas were declared, rewritten with them; and a ``store.json``
of a format this code does not know (a newer mimucal's), refused with one line.

Format 1.0 is migrated under the caller's lock: each flat table is split into its lot files,
then the flat file is removed. A flat file that is present is authoritative (a migration
that died half-way is redone)."""

from __future__ import annotations

import json
from pathlib import Path

import pandas as pd
import pyarrow as pa
import pyarrow.parquet as pq

from schemas.calibration_file import write_json_atomic
from schemas.store_frames import FORMAT_FILE, TABLES, normalise, sorted_rows, split_by_lot
from schemas.store_io import StoreError, fsync_dir, iso, utc_now, write_parquet_atomic, write_table_atomic
from schemas.store_tables import conform, schema_problem

STORE_FORMAT_VERSION = "2.0"
LEGACY_FORMAT_VERSION = "1.0"  # flat <name>.parquet at the root; read, and migrated on write
KNOWN_FORMAT_VERSIONS = (LEGACY_FORMAT_VERSION, STORE_FORMAT_VERSION)


def _version_key(text: str) -> tuple[int, ...] | None:
    try:
        return tuple(int(x) for x in text.split("."))
    except ValueError:
        return None


def stored_format_problem(root: Path) -> str | None:
    """Why this code must not use the store at ``root`` (None: it may): its ``store.json``
    names a format this code does not know, e.g. one written by a newer mimucal. A missing or
    unreadable ``store.json`` is not this function's business (:meth:`verify` names it)."""
    path = Path(root) / FORMAT_FILE
    try:
        doc = json.loads(path.read_bytes()[:65536].decode("utf-8"))
    except (OSError, ValueError):
        return None
    version = doc.get("format_version") if isinstance(doc, dict) else None
    if not isinstance(version, str) or version in KNOWN_FORMAT_VERSIONS:
        return None
    key, newest = _version_key(version), _version_key(STORE_FORMAT_VERSION)
    if key is not None and key > newest:
        return (
            f"results store {root} is format {version} ({path}), newer than the format "
            f"{STORE_FORMAT_VERSION} this mimucal writes: use the mimucal that wrote it, or a newer one"
        )
    return (
        f"results store {root} has an unknown format {version!r} ({path}); this mimucal reads "
        f"formats {', '.join(KNOWN_FORMAT_VERSIONS)}"
    )


class LegacyFormat:
    """Format detection and migration of the store rooted at ``self.root``."""

    root: Path
    # whether this object's first write has checked every lot file against the declared
    # schemas (see _migrate)
    _schemas_checked: bool
    _format_checked: bool

    @property
    def format_path(self) -> Path:
        return self.root / FORMAT_FILE

    def legacy_path(self, name: str) -> Path:
        """Where format 1.0 kept the whole table (``<name>.parquet`` at the root)."""
        self._check(name)
        return self.root / f"{name}.parquet"

    def format_version(self) -> str | None:
        """``1.0`` while any flat format-1.0 table is present (not yet migrated), ``2.0`` once
        written by this code, None for an empty root."""
        if any(self.legacy_path(n).exists() for n in TABLES):
            return LEGACY_FORMAT_VERSION
        if self.format_path.exists() or self.tables_dir.is_dir():
            return STORE_FORMAT_VERSION
        return None

    def check_format(self) -> None:
        """Refuse (:class:`StoreError`, one line) a store of a format this code does not
        know; checked once per store object, before its first read or write."""
        if self._format_checked:
            return
        why = stored_format_problem(self.root)
        if why:
            raise StoreError(why)
        self._format_checked = True

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

    def _migrate(self) -> list[str]:
        """Split every flat format-1.0 table into its lot files, then remove the flat file;
        mark the root as format 2.0. Runs on the first write (under the caller's lock);
        idempotent, and a migration that died half-way is redone from the flat file. A store
        of a format this code does not know is refused first (:meth:`check_format`)."""
        self.check_format()
        migrated = []
        for name in TABLES:
            legacy = self.legacy_path(name)
            if not legacy.exists():
                continue
            df = sorted_rows(normalise(pq.read_table(legacy).to_pandas(), name))
            d = self.table_dir(name)
            d.mkdir(parents=True, exist_ok=True)
            by_lot = split_by_lot(df)
            for lot, path in self.partitions(name).items():  # left by a dead migration
                if lot not in by_lot:
                    path.unlink()
            for lot, part in by_lot.items():
                write_parquet_atomic(part, self.partition_path(name, lot), name)
            self._keep_readable(name)
            fsync_dir(d)
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
