"""The store checks itself: what is wrong with it, one line per problem (every run checks
before writing anything), and damaged files moved aside for a person to look at."""

from __future__ import annotations

import json
import os
from pathlib import Path

import pyarrow as pa
import pyarrow.parquet as pq

from schemas.store_archive import calibration_file_problem
from schemas.store_frames import EMPTY_FILE, TABLES
from schemas.store_io import REPAIR_HINT, TIMESTAMP_FORMAT, StoreError, utc_now
from schemas.store_legacy import stored_format_problem
from schemas.store_tables import TABLE_SCHEMAS


class StoreCheck:
    """The self-check of the store rooted at ``self.root``."""

    root: Path

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
        unknown = stored_format_problem(self.root)
        if unknown:  # repair cannot help: this code must not touch the store
            return [unknown]
        units_ok = True
        for name in TABLES:
            empty = self.table_dir(name) / EMPTY_FILE
            files = (
                ([self.legacy_path(name)] if self.legacy_path(name).exists() else [])
                + list(self.partitions(name).values())
                + ([empty] if empty.exists() else [])
            )
            for path in files:
                why = table_file_problem(path, name)
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


def table_file_problem(path: Path, name: str) -> str | None:
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
