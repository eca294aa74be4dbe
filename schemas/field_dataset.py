"""Field recordings in the dataset: units calibrated without a turntable.

Layout (an optional addition beside the acquisition contract's ``rep=<n>`` sessions)::

    <root>/lot=<lot>/unit=<unit>/field/<recording>            one log file (CSV/text, any
                                                               format schemas.importers reads)
    <root>/lot=<lot>/unit=<unit>/field/<recording>/           or a directory of two text files
                                        acc.txt gyro.txt       (IMU-TK's pair, t x y z)
    <root>/lot=<lot>/unit=<unit>/field/<recording>.json       optional: options of this recording
    <root>/lot=<lot>/unit=<unit>/field/field.json             optional: options of the unit
    <root>/lot=<lot>/field.json                               optional: options of the lot

Options (JSON object; a recording's own file overrides its unit's, which overrides its
lot's): the ``mimucal field`` options, see :data:`FIELD_OPTIONS`. The recordings of a unit,
in name order, are its repetitions 1, 2, ...: their calibrations are averaged as a
turntable unit's repetitions are. Names starting with ``.`` or ``_`` are ignored.

Errors never raise out of :func:`find_field_recordings`: a bad name or options file becomes
an ``E_BAD_PATH`` :class:`SessionError` in the returned list; reading a recording
(:func:`read_field_recording`) raises :class:`SessionError` naming the recording and file.
"""

from __future__ import annotations

import hashlib
import json
import os
from dataclasses import dataclass, field
from fractions import Fraction
from pathlib import Path
from typing import Any

from calib_core.steps import SessionKey
from schemas.errors import E_BAD_PATH, SessionError
from schemas.hive import FIELD_DIR, file_digest
from schemas.hive import parse_part as _parse_part
from schemas.hive import visible_dirs as _visible_dirs

OPTIONS_FILE = "field.json"  # the options shared by a unit's (in field/) or a lot's recordings
IMUTK_PAIR = ("acc.txt", "gyro.txt")  # a recording directory: IMU-TK's two files

# option -> (type, default): the options of ``mimucal field`` (same meaning and defaults)
FIELD_OPTIONS: dict[str, tuple[type | tuple[type, ...], Any]] = {
    "columns": (str, None),  # "ax=0,ay=1,...": CHANNEL=SOURCE (name or 0-based position)
    "rate": ((int, float), None),  # Hz, when no time column is mapped and no Fs preamble line
    "time_scale": ((int, float), 1.0),
    "gyro_unit": (str, "LSB"),
    "accel_unit": (str, "LSB"),
    "g_local": ((int, float), 9.80665),
    "accel_range": (str, None),  # "2g": int16 full scale, starting scale range/32768
    "gyro_range": (str, None),  # "250dps"; samples at +/-32767 counts are clipped
    "init_static": ((int, float), None),  # s at rest at the start (default: preamble, else quietest)
    "acc_bias": ((int, float), None),
    "acc_scale": ((int, float), None),
    "gyro_scale": ((int, float), None),
    "window": ((int, float), 0.25),
    "min_pose": ((int, float), 1.0),
    "multiplier": ((int, float), 3.0),
    "drift": (str, "auto"),
    "gyro_g_sensitivity": (str, "auto"),
    "misalignment_prior": ((int, float), 0.01),
    "session_start": (str, None),  # ISO 8601 UTC: when the recording was made
}


@dataclass(frozen=True)
class FieldRecordingRef:
    """One field recording of a unit: its identity (``rep`` = its place in name order), the
    file(s) to read, and its options merged from the lot, unit and recording files."""

    key: SessionKey
    path: Path  # the log file, or the directory of an IMU-TK pair
    files: tuple[Path, ...]
    options: dict[str, Any] = field(default_factory=dict)
    option_files: tuple[Path, ...] = ()

    @property
    def name(self) -> str:
        return self.path.name

    def __str__(self) -> str:
        return f"{self.key} (field recording {self.name})"


def _bad(path: Path, reason: str) -> SessionError:
    return SessionError(E_BAD_PATH, str(path), path.name, reason)


def read_options(path: Path) -> dict[str, Any]:
    """An options file: a JSON object of known options of the right types (ValueError
    naming the file and the problem otherwise)."""
    try:
        doc = json.loads(path.read_text())
    except (OSError, ValueError) as exc:
        raise ValueError(f"options file {path}: not readable JSON ({exc})") from None
    if not isinstance(doc, dict):
        raise ValueError(f"options file {path}: expected a JSON object")
    for k, v in doc.items():
        if k not in FIELD_OPTIONS:
            raise ValueError(f"options file {path}: unknown option {k!r} (known: {', '.join(FIELD_OPTIONS)})")
        kind = FIELD_OPTIONS[k][0]
        if isinstance(v, str) and kind == (int, float):  # "1/6258", as on the command line
            try:
                v = doc[k] = float(Fraction(v.strip()))
            except (ValueError, ZeroDivisionError):
                raise ValueError(f"options file {path}: option {k!r} is not a number ({v!r})") from None
        if v is not None and (not isinstance(v, kind) or isinstance(v, bool)):
            raise ValueError(f"options file {path}: option {k!r} has the wrong type ({type(v).__name__})")
    return doc


def default_options() -> dict[str, Any]:
    return {k: d for k, (_, d) in FIELD_OPTIONS.items()}


def _visible(path: Path) -> list[Path]:
    try:
        return sorted((p for p in path.iterdir() if not p.name.startswith((".", "_"))), key=lambda p: p.name)
    except OSError:
        return []


def find_field_recordings(
    root: Path | str, lot: str | None = None, unit: str | None = None
) -> tuple[list[FieldRecordingRef], list[SessionError]]:
    """Every unit's field recordings under ``root`` (lot and unit names as
    :func:`schemas.dataset.find_sessions` checks them), sorted by lot, unit, rep; one
    ``E_BAD_PATH`` error per unreadable options file or recording directory that is not an
    IMU-TK pair (the unit's other recordings are still found)."""
    root = Path(root)
    refs: list[FieldRecordingRef] = []
    errors: list[SessionError] = []
    if not root.is_dir():
        return [], []
    for lot_dir in _visible_dirs(root):
        lot_id, why = _parse_part(lot_dir.name, "lot")
        if why or (lot is not None and lot_id != lot):
            continue  # bad names are find_sessions' to report
        for unit_dir in _visible_dirs(lot_dir):
            unit_id, why = _parse_part(unit_dir.name, "unit")
            fdir = unit_dir / FIELD_DIR
            if why or (unit is not None and unit_id != unit) or not fdir.is_dir():
                continue
            base = default_options()
            option_files = []
            try:
                for p in (lot_dir / OPTIONS_FILE, fdir / OPTIONS_FILE):
                    if p.is_file():
                        base.update(read_options(p))
                        option_files.append(p)
            except ValueError as exc:
                errors.append(_bad(fdir, str(exc)))
                continue
            entries = _visible(fdir)
            names = {p.name for p in entries}
            recordings = [
                p
                for p in entries
                if p.name != OPTIONS_FILE and not (p.suffix == ".json" and (p.name[: -len(".json")] in names))
            ]
            for rep, rec in enumerate(recordings, start=1):
                key = SessionKey(lot_id, unit_id, rep)
                if rec.is_dir():
                    files = tuple(rec / n for n in IMUTK_PAIR)
                    if not all(f.is_file() for f in files):
                        errors.append(
                            _bad(
                                rec,
                                f"a field recording directory holds IMU-TK's pair {' and '.join(IMUTK_PAIR)}",
                            )
                        )
                        continue
                else:
                    files = (rec,)
                opts, used = dict(base), list(option_files)
                own = rec.with_name(rec.name + ".json")
                if own.is_file():
                    try:
                        opts.update(read_options(own))
                    except ValueError as exc:
                        errors.append(_bad(rec, str(exc)))
                        continue
                    used.append(own)
                refs.append(FieldRecordingRef(key, rec, files, opts, tuple(used)))
    refs.sort(key=lambda r: (r.key.lot, r.key.unit, r.key.rep))
    return refs, errors


def field_fingerprint(ref: FieldRecordingRef) -> str:
    """Identity of a recording's content: its file(s) and options files, name, size and
    blake2b digest each (as :func:`schemas.dataset.fingerprint` for a session): a changed
    byte of the log or of an option recalibrates the unit."""
    h = hashlib.sha256()
    h.update(f"field:{ref.name};".encode())
    for p in (*ref.files, *ref.option_files):
        try:
            h.update(f"{p.name}:{os.stat(p).st_size}:{file_digest(str(p))};".encode())
        except FileNotFoundError:
            h.update(f"{p.name}:missing;".encode())
    return h.hexdigest()[:32]


def read_field_recording(ref: FieldRecordingRef):
    """The recording as a :class:`schemas.importers.RawRecording` (IMU-TK pair or one
    table). Raises :class:`SessionError` naming the session and the file."""
    from schemas.importers import parse_column_mapping, read_imutk_pair, read_table_recording

    o = ref.options
    try:
        if len(ref.files) == 2:
            return read_imutk_pair(ref.files[0], ref.files[1], o["gyro_unit"], o["accel_unit"], o["g_local"])
        try:
            mapping = parse_column_mapping(o["columns"]) if o["columns"] else None
        except ValueError as exc:
            raise SessionError(E_BAD_PATH, str(ref.key), ref.name, f"option 'columns': {exc}") from None
        return read_table_recording(
            ref.files[0],
            mapping,
            o["gyro_unit"],
            o["accel_unit"],
            rate_hz=o["rate"],
            g_local=o["g_local"],
            time_scale=o["time_scale"],
        )
    except SessionError as exc:
        if str(ref.key) in str(exc):
            raise
        raise SessionError(exc.code, str(ref.key), exc.file, exc.reason, column=exc.column) from None
