"""The calibration archive: ``calibrations/<unit>/<YYYYmmddTHHMMSS.ffffffZ>.json``, every
calibration ever produced (never overwritten), and which of them is valid at a given time."""

from __future__ import annotations

import json
import os
from datetime import UTC, datetime, timedelta
from pathlib import Path
from typing import Any

from schemas.store_io import TIMESTAMP_FORMAT, iso, parse_when, store_default, utc_now


class CalibrationNotFound(LookupError):
    """No calibration of the unit matches the request."""


class CalibrationArchive:
    """The calibration files of the store rooted at ``self.root``."""

    root: Path

    @property
    def calibrations_dir(self) -> Path:
        return self.root / "calibrations"

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
            return save_calibration(cal, path, extra, extra_nonfinite="null", default=store_default)
        return save_calibration(cal, path, extra)

    def calibration_files(self, unit: str) -> list[tuple[datetime, Path]]:
        """(production time, path) of every calibration file of ``unit``, oldest first."""
        return calibration_files(self.root, unit)

    def find_calibration(self, unit: str, at: datetime | None = None, before_after: str = "before") -> Path:
        return find_calibration(self.root, unit, at, before_after)


def calibration_files(root: Path, unit: str) -> list[tuple[datetime, Path]]:
    """(production time, path) of every calibration file of ``unit`` under ``root``, oldest
    first (the time is the file name)."""
    d = Path(root) / "calibrations" / unit
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


def calibration_times(results: Path | str, unit: str) -> list[tuple[datetime, datetime, Path, str]]:
    """Every calibration file of ``unit`` as (time, produced, path, source of the time),
    sorted by time then production. The time of a calibration is when its unit was measured:
    ``provenance.acquired_at`` (its sessions' last ``session_start``; source
    ``"session_start"``), else when it was produced (the file name, source
    ``"processing time"``: sessions without ``session_start``, or files of older code)."""
    out = []
    for produced, path in calibration_files(Path(results), unit):
        when, source = produced, "processing time"
        try:
            prov = json.loads(path.read_text()).get("provenance") or {}
            if isinstance(prov.get("acquired_at"), str):
                when, source = parse_when(prov["acquired_at"]), "session_start"
        except (OSError, ValueError, AttributeError):
            pass
        out.append((when, produced, path, source))
    return sorted(out, key=lambda x: (x[0], x[1]))


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
