"""The results store: what the nightly flow, reruns and reports share, under ``--results``.

Layout (all Parquet written with a temp file in the same directory and ``os.replace``)::

    sessions.parquet       one row per session ever seen: status, error, fingerprint, run id
    parameters.parquet     one row per lot/unit/rep/model/parameter
    summary.parquet        one row per lot/unit/model/parameter over reps, outlier flags, stale
    units.parquet          one row per unit: state (calibrated | stale | failed), why, file
    residuals.parquet      per-step residuals of every calibrated session
    compensation.parquet   xu2016 Table 3 rows of every calibrated session
    discovery.parquet      one row per unit and effect found by model discovery
    calibrations/<unit>/<YYYYmmddTHHMMSS.ffffffZ>.json   every calibration ever produced
    runs/<run_id>.json     run log (start, end, counts, progress, errors)
    reports/               written by ``reports.*``
    .lock                  held (flock) by the run writing the store

Updating a unit replaces only that unit's rows. A unit whose recalibration fails keeps its
last good parameters, summary and calibration files; ``units.parquet`` and the ``stale`` /
``stale_reason`` columns of ``summary.parquet`` say that they are stale and why, and
``sessions.parquet`` holds the failures.
"""
from __future__ import annotations

import errno
import fcntl
import json
import os
import socket
import tempfile
import time
from contextlib import contextmanager
from dataclasses import dataclass
from datetime import datetime, timedelta, timezone
from pathlib import Path
from typing import Any, Iterator

import numpy as np
import pandas as pd
import pyarrow as pa
import pyarrow.parquet as pq

from calib_core.results import to_jsonable
from schemas.calibration_file import write_json_atomic

STORE_FORMAT_VERSION = "1.0"
TIMESTAMP_FORMAT = "%Y%m%dT%H%M%S.%fZ"

# column order of each table (documented in docs/flows.md); extra columns are kept
TABLE_COLUMNS: dict[str, list[str]] = {
    "sessions": ["lot", "unit", "rep", "status", "error_code", "message", "warnings",
                 "fingerprint", "run_id", "path", "calibrated_at"],
    "parameters": ["lot", "unit", "rep", "model", "parameter", "value", "stderr",
                   "unit_of_measure", "code_version", "run_id"],
    "summary": ["lot", "unit", "model", "parameter", "mean", "std", "min", "max", "n_reps",
                "unit_of_measure", "flagged", "flag_reason", "score", "lot_median", "stale",
                "stale_reason", "run_id"],
    "units": ["lot", "unit", "state", "reason", "n_sessions", "n_ok", "n_warned", "n_failed",
              "calibration_file", "calibrated_at", "run_id", "updated_at", "flagged",
              "flag_reason"],
    "residuals": ["lot", "unit", "rep"],
    "compensation": ["lot", "unit", "rep"],
    "discovery": ["lot", "unit", "effect"],
    # zhang2017 navigation drift of a unit's own fitted model (written by reruns)
    "navigation": ["lot", "unit", "case", "t", "vel_err", "pos_err"],
}
TABLES = tuple(TABLE_COLUMNS)
# dtypes of key columns, so that empty tables and concatenations agree
_KEY_DTYPES = {"lot": "string", "unit": "string", "rep": "Int64"}


class StoreLockedError(RuntimeError):
    """Another run holds the results root."""


class CalibrationNotFound(LookupError):
    """No calibration of the unit matches the request."""


def utc_now() -> datetime:
    return datetime.now(timezone.utc)


def iso(dt: datetime) -> str:
    return dt.astimezone(timezone.utc).isoformat().replace("+00:00", "Z")


def parse_when(text: str) -> datetime:
    """ISO 8601 date or date-time; naive values are UTC."""
    t = text.strip().replace("Z", "+00:00")
    dt = datetime.fromisoformat(t)
    if dt.tzinfo is None:
        dt = dt.replace(tzinfo=timezone.utc)
    return dt.astimezone(timezone.utc)


def _current_umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


_UMASK = _current_umask()


# --- atomic writes ------------------------------------------------------------------------------
def write_parquet_atomic(df: pd.DataFrame, path: Path) -> None:
    """Parquet via a temp file in the same directory, fsync, then ``os.replace``."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    table = pa.Table.from_pandas(df, preserve_index=False)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    os.close(fd)
    try:
        pq.write_table(table, tmp, compression="zstd")
        with open(tmp, "rb") as fh:
            os.fsync(fh.fileno())
        os.chmod(tmp, 0o666 & ~_UMASK)  # mkstemp makes 0600; the store is read by others
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise


def _normalise(df: pd.DataFrame, name: str) -> pd.DataFrame:
    cols = TABLE_COLUMNS[name]
    df = df.copy()
    for c in cols:
        if c not in df.columns:
            df[c] = pd.Series([None] * len(df), dtype=_KEY_DTYPES.get(c, "object"))
    for c, dt in _KEY_DTYPES.items():
        if c in df.columns:
            df[c] = df[c].astype(dt)
    extra = [c for c in df.columns if c not in cols]
    return df[cols + extra]


# --- the store ------------------------------------------------------------------------------------
@dataclass
class ResultsStore:
    root: Path

    def __post_init__(self) -> None:
        self.root = Path(self.root)

    # paths
    def table_path(self, name: str) -> Path:
        if name not in TABLE_COLUMNS:
            raise KeyError(f"unknown table {name!r}; tables: {', '.join(TABLES)}")
        return self.root / f"{name}.parquet"

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

    def exists(self) -> bool:
        return self.table_path("sessions").exists()

    # tables
    def read(self, name: str) -> pd.DataFrame:
        """A table (an empty frame with its columns when it was never written)."""
        path = self.table_path(name)
        if not path.exists():
            return _normalise(pd.DataFrame(), name)
        return _normalise(pq.read_table(path).to_pandas(), name)

    def write(self, name: str, df: pd.DataFrame) -> None:
        df = _normalise(df, name)
        sort = [c for c in ("lot", "unit", "rep", "model", "parameter", "effect") if c in df]
        if len(df) and sort:
            df = df.sort_values(sort, kind="stable").reset_index(drop=True)
        write_parquet_atomic(df, self.table_path(name))

    def replace_units(self, name: str, new_rows: pd.DataFrame | None,
                      units: set[tuple[str, str]]) -> pd.DataFrame:
        """Replace every row of the given (lot, unit)s by ``new_rows``; other rows unchanged."""
        old = self.read(name)
        if units and len(old):
            keys = pd.MultiIndex.from_frame(old[["lot", "unit"]].astype(object))
            keep = ~keys.isin(list(units))
            old = old[keep]
        parts = [p for p in (old, None if new_rows is None else _normalise(new_rows, name))
                 if p is not None and len(p)]
        df = pd.concat(parts, ignore_index=True) if parts else _normalise(pd.DataFrame(), name)
        self.write(name, df)
        return df

    def update_rows(self, name: str, units: set[tuple[str, str]], **values: Any) -> None:
        """Set columns of the rows of the given units (e.g. ``stale=True``)."""
        df = self.read(name)
        if not len(df) or not units:
            return
        keys = pd.MultiIndex.from_frame(df[["lot", "unit"]].astype(object))
        hit = keys.isin(list(units))
        for col, v in values.items():
            if col not in df:
                df[col] = None
            if isinstance(v, bool):
                df[col] = df[col].astype("boolean")
            elif isinstance(v, str):
                df[col] = df[col].astype(object)
            df.loc[hit, col] = v
        self.write(name, df)

    # fingerprints of the last run: (lot, unit, rep) -> fingerprint
    def fingerprints(self) -> dict[tuple[str, str, int], str]:
        df = self.read("sessions")
        return {(str(r.lot), str(r.unit), int(r.rep)): str(r.fingerprint)
                for r in df.itertuples() if pd.notna(r.rep)}

    def lots(self) -> list[str]:
        return sorted(self.read("units")["lot"].dropna().unique().tolist())

    # calibrations
    def save_calibration(self, cal, unit: str, extra: dict[str, Any],
                         when: datetime | None = None) -> Path:
        """A new ``calibrations/<unit>/<timestamp>.json``; never overwrites an existing one."""
        from schemas.calibration_file import save_calibration
        when = when or utc_now()
        d = self.calibrations_dir / unit
        d.mkdir(parents=True, exist_ok=True)
        for _ in range(1000):
            path = d / f"{when.astimezone(timezone.utc).strftime(TIMESTAMP_FORMAT)}.json"
            if not path.exists():
                break
            when = when + timedelta(microseconds=1)  # same instant twice: keep both
        return save_calibration(cal, path, extra)

    def calibration_files(self, unit: str) -> list[tuple[datetime, Path]]:
        d = self.calibrations_dir / unit
        out = []
        if d.is_dir():
            for p in d.glob("*.json"):
                try:
                    ts = datetime.strptime(p.stem, TIMESTAMP_FORMAT).replace(tzinfo=timezone.utc)
                except ValueError:
                    continue
                out.append((ts, p))
        return sorted(out)

    def find_calibration(self, unit: str, at: datetime | None = None,
                         before_after: str = "before") -> Path:
        return find_calibration(self.root, unit, at, before_after)

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
    def lock(self, owner: str, wait: bool = False, timeout: float | None = None,
             poll_s: float = 0.5) -> Iterator[None]:
        """Hold the results root for one run. ``flock`` is released by the kernel if the
        process dies, so a crashed run never leaves the store locked. A second run is refused
        with :class:`StoreLockedError` naming the holder, or waits (``wait=True``)."""
        self.root.mkdir(parents=True, exist_ok=True)
        fd = os.open(self.lock_path, os.O_RDWR | os.O_CREAT, 0o644)
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
                            f"--wait") from None
                    time.sleep(poll_s)
            info = json.dumps({"owner": owner, "pid": os.getpid(), "host": socket.gethostname(),
                               "since": iso(utc_now())})
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
        for d in (self.root, self.runs_dir, *(self.calibrations_dir.glob("*")
                                                if self.calibrations_dir.is_dir() else ())):
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
        return (f"run {info.get('owner')} (pid {info.get('pid')} on {info.get('host')}, "
                f"since {info.get('since')})")


def find_calibration(results: Path | str, unit: str, at: datetime | None = None,
                     before_after: str = "before") -> Path:
    """The calibration file of ``unit`` valid at ``at`` (default: now).

    ``before`` (default): the latest calibration made at or before ``at``; ``after``: the
    earliest at or after; ``closest``: the nearest either way (imucal's
    ``find_closest_calibration_info_to_date`` with ``before_after=None``). The time of a
    calibration is when it was produced (its file name, UTC)."""
    if before_after not in ("before", "after", "closest"):
        raise ValueError("before_after must be 'before', 'after' or 'closest'")
    at = at or utc_now()
    if at.tzinfo is None:
        at = at.replace(tzinfo=timezone.utc)
    files = ResultsStore(Path(results)).calibration_files(unit)
    if not files:
        raise CalibrationNotFound(f"no calibration of unit {unit!r} under "
                                  f"{Path(results) / 'calibrations' / unit}")
    if before_after == "before":
        cands = [f for f in files if f[0] <= at]
        if not cands:
            raise CalibrationNotFound(f"unit {unit!r}: no calibration at or before {iso(at)} "
                                      f"(first one is {iso(files[0][0])})")
        return cands[-1][1]
    if before_after == "after":
        cands = [f for f in files if f[0] >= at]
        if not cands:
            raise CalibrationNotFound(f"unit {unit!r}: no calibration at or after {iso(at)} "
                                      f"(last one is {iso(files[-1][0])})")
        return cands[0][1]
    return min(files, key=lambda f: abs((f[0] - at).total_seconds()))[1]


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
