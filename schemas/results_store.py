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
migrated to 2.0 by the first write (callers hold the lock); a ``store.json`` of a format this
code does not know (a newer mimucal's) is refused with one line (:mod:`schemas.store_legacy`).

One module per concern; :class:`ResultsStore` is their sum over one root:
:mod:`schemas.store_lot_tables` (the tables' lot files), :mod:`schemas.store_frames` (frames
normalised to a table, lot file names), :mod:`schemas.store_io` (atomic writes, time
stamps), :mod:`schemas.store_legacy` (other formats), :mod:`schemas.store_archive` (the
calibration archive), :mod:`schemas.store_runs` (run logs), :mod:`schemas.store_caches`
(caches and the QA configuration), :mod:`schemas.store_lock` (the lock),
:mod:`schemas.store_check` (the self-check).

Updating a unit replaces only that unit's rows. A unit whose recalibration fails keeps its
last good parameters, summary and calibration files; the ``units`` table and the ``stale`` /
``stale_reason`` columns of ``summary`` say that they are stale and why, and ``sessions``
holds the failures.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

from schemas.calibration_file import write_json_atomic
from schemas.store_archive import (
    CalibrationArchive,
    CalibrationNotFound,
    calibration_file_problem,
    calibration_times,
    find_calibration,
)
from schemas.store_caches import FLAG_STATE_METADATA_KEY, StoreCaches
from schemas.store_check import StoreCheck, table_file_problem
from schemas.store_frames import EMPTY_FILE, TABLE_COLUMNS, TABLES, lot_of_partition, partition_file_name
from schemas.store_io import (
    REPAIR_HINT,
    ROW_GROUP_ROWS,
    TIMESTAMP_FORMAT,
    StoreError,
    iso,
    jsonable,
    parse_when,
    utc_now,
    write_parquet_atomic,
    write_table_atomic,
)
from schemas.store_legacy import LEGACY_FORMAT_VERSION, STORE_FORMAT_VERSION, LegacyFormat
from schemas.store_lock import StoreLock, StoreLockedError, stat_is_regular
from schemas.store_lot_tables import LotTables
from schemas.store_runs import RunLogs

__all__ = [
    "EMPTY_FILE",
    "FLAG_STATE_METADATA_KEY",
    "LEGACY_FORMAT_VERSION",
    "REPAIR_HINT",
    "ROW_GROUP_ROWS",
    "STORE_FORMAT_VERSION",
    "TABLES",
    "TABLE_COLUMNS",
    "TIMESTAMP_FORMAT",
    "CalibrationNotFound",
    "ResultsStore",
    "StoreError",
    "StoreLockedError",
    "calibration_file_problem",
    "calibration_times",
    "find_calibration",
    "iso",
    "jsonable",
    "lot_of_partition",
    "parse_when",
    "partition_file_name",
    "stat_is_regular",
    "table_file_problem",
    "utc_now",
    "write_json_atomic",
    "write_parquet_atomic",
    "write_table_atomic",
]


@dataclass
class ResultsStore(LotTables, LegacyFormat, CalibrationArchive, RunLogs, StoreCaches, StoreLock, StoreCheck):
    """The results store under ``root``: each concern's methods come from its module."""

    root: Path
    _schemas_checked: bool = field(default=False, init=False, repr=False, compare=False)
    _format_checked: bool = field(default=False, init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        self.root = Path(self.root)

    @property
    def reports_dir(self) -> Path:
        return self.root / "reports"
