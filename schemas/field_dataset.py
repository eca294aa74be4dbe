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

import json
import os
from dataclasses import dataclass, field
from fractions import Fraction
from pathlib import Path
from typing import Any, ClassVar

from calib_core.steps import SessionKey
from schemas.contract import G_LOCAL_PLAUSIBLE, session_start_problem
from schemas.errors import E_BAD_METADATA, E_BAD_OPTION, E_BAD_PATH, E_UNREADABLE_FILE, SessionError
from schemas.hive import FIELD_DIR, file_digest, fingerprint_of, link_problem
from schemas.hive import bad_path as _bad
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
    error: SessionError | None = None  # why the recording cannot be used (it fails by name)

    @property
    def name(self) -> str:
        return self.path.name

    kind: ClassVar[str] = "field"  # the unit pipeline that calibrates it (flows.unit_pipeline)

    def __str__(self) -> str:
        return f"{self.key} (field recording {self.name})"

    def content_fingerprint(self, cache=None) -> str:
        """:func:`field_fingerprint` (``cache`` unused: a recording is hashed whole)."""
        return field_fingerprint(self)


class OptionError(ValueError):
    """An options file or value that cannot be used: ``code`` (``E_BAD_OPTION``,
    ``E_BAD_METADATA`` for a bad ``session_start``, ``E_BAD_PATH`` for a refused file) and a
    one-line reason naming the file and the option. Never quotes more of the file than a short
    escaped excerpt."""

    def __init__(self, reason: str, code: str = E_BAD_OPTION):
        self.code = code
        super().__init__(reason)


MAX_OPTIONS_BYTES = 64 * 1024  # an options file is a few lines
MAX_JSON_DEPTH = 16  # an options document is one object of scalars
MAX_OPTION_TEXT = 256  # characters of one string option
# A field calibration is minutes of hand-held poses (the real MPU-6050 log: 0.3 MB; IMU-TK's
# Xsens pair: 2 x 3.2 MB). A log this large is not one: refused before it is read (parsing it
# would take minutes and gigabytes), as is its digest (the fingerprint takes its size only).
MAX_RECORDING_BYTES = 256 * 1024 * 1024

# option -> (low, high, low inclusive): numbers must be finite and inside
OPTION_RANGES: dict[str, tuple[float, float, bool]] = {
    "rate": (0.0, 1e5, False),  # Hz
    "time_scale": (0.0, 1e6, False),
    "g_local": (G_LOCAL_PLAUSIBLE[0], G_LOCAL_PLAUSIBLE[1], True),  # m/s^2, anywhere on Earth
    "init_static": (0.0, 86400.0, True),  # s; 0: no initial rest
    "acc_bias": (-1e9, 1e9, True),  # raw units
    "acc_scale": (0.0, 1e6, False),  # m/s^2 per raw unit: a zero scale is no sensor
    "gyro_scale": (0.0, 1e6, False),  # rad/s per raw unit
    "window": (0.0, 60.0, False),  # s
    "min_pose": (0.0, 3600.0, False),  # s
    "multiplier": (0.0, 1e3, False),
    "misalignment_prior": (0.0, 1.0, True),  # rad; 0: no prior
}
ON_OFF_AUTO = ("auto", "on", "off")
GYRO_UNITS_IN = ("deg/s", "dps", "rad/s", "LSB", "counts", "V")
ACCEL_UNITS_IN = ("g", "mg", "m/s^2", "m/s2", "LSB", "counts", "V")


def loads_bounded(text: str, max_depth: int = MAX_JSON_DEPTH) -> Any:
    """``json.loads`` of a document nested at most ``max_depth`` arrays/objects deep
    (ValueError otherwise): the depth is counted in one pass before decoding, so a hostile
    100,000-deep document never reaches the recursive decoder."""
    depth, in_str, esc = 0, False, False
    for ch in text:
        if in_str:
            if esc:
                esc = False
            elif ch == "\\":
                esc = True
            elif ch == '"':
                in_str = False
        elif ch == '"':
            in_str = True
        elif ch in "[{":
            depth += 1
            if depth > max_depth:
                raise ValueError(f"nested more than {max_depth} levels deep")
        elif ch in "]}":
            depth -= 1
    return json.loads(text)


def option_problem(name: str, value: Any) -> str | None:
    """Why ``value`` is not a usable value of option ``name`` (type, finite, range, known
    words, a column mapping sending two channels to one column), or None when it is."""
    import math

    from schemas.importers import parse_column_mapping, parse_range

    kind = FIELD_OPTIONS[name][0]
    if value is None:
        return None
    if not isinstance(value, kind) or isinstance(value, bool):
        return f"has the wrong type ({type(value).__name__})"
    if isinstance(value, str):
        if len(value) > MAX_OPTION_TEXT:
            return f"is longer than {MAX_OPTION_TEXT} characters"
        if name == "session_start":
            return session_start_problem(value)
        if name in ("drift", "gyro_g_sensitivity") and value not in ON_OFF_AUTO:
            return f"{value!r} is not one of {', '.join(ON_OFF_AUTO)}"
        if name == "gyro_unit" and value not in GYRO_UNITS_IN:
            return f"{value!r} is not one of {', '.join(GYRO_UNITS_IN)}"
        if name == "accel_unit" and value not in ACCEL_UNITS_IN:
            return f"{value!r} is not one of {', '.join(ACCEL_UNITS_IN)}"
        try:
            if name in ("accel_range", "gyro_range"):
                parse_range(value, "accel" if name == "accel_range" else "gyro")
            if name == "columns":
                mapping = parse_column_mapping(value)
                sources: dict[str, list[str]] = {}
                for ch, src in mapping.items():
                    sources.setdefault(src, []).append(ch)
                shared = {src: chs for src, chs in sources.items() if len(chs) > 1}
                if shared:
                    src, chs = next(iter(shared.items()))
                    return (
                        f"maps {', '.join(chs)} to the same column {src[:40]!r}; each channel needs its own"
                    )
        except ValueError as exc:
            return str(exc)[:200]
        return None
    v = float(value)
    lo, hi, lo_in = OPTION_RANGES[name]
    if not math.isfinite(v):
        return f"= {value!r} is not a finite number"
    if v > hi or v < lo or (v == lo and not lo_in):
        left = "[" if lo_in else "("
        return f"= {value!r} is outside {left}{lo:g}, {hi:g}]"
    return None


def check_options(doc: dict[str, Any], where: str) -> dict[str, Any]:
    """``doc`` when every option is known and its value usable; :class:`OptionError` naming
    ``where`` and the option otherwise (``E_BAD_METADATA`` for ``session_start``)."""
    for k, v in doc.items():
        if k not in FIELD_OPTIONS:
            raise OptionError(f"{where}: unknown option {str(k)[:40]!r} (known: {', '.join(FIELD_OPTIONS)})")
        kind = FIELD_OPTIONS[k][0]
        if isinstance(v, str) and kind == (int, float):  # "1/6258", as on the command line
            try:
                v = doc[k] = float(Fraction(v.strip()[:MAX_OPTION_TEXT]))
            except (ValueError, ZeroDivisionError, OverflowError):
                raise OptionError(f"{where}: option {k!r} is not a number ({v[:40]!r})") from None
        why = option_problem(k, v)
        if why:
            code = E_BAD_METADATA if k == "session_start" else E_BAD_OPTION
            raise OptionError(f"{where}: option {k!r} {why}", code)
    return doc


def file_problem(path: Path, root: Path | None, follow_symlinks: bool, want_dir: bool = False) -> str | None:
    """Why the dataset file ``path`` must not be opened, or None: a symbolic link on its way
    below ``root`` (refused unless ``follow_symlinks``; followed, it must stay inside
    ``root``), or not a regular file (a FIFO, a device such as ``/dev/zero``) or directory
    (``want_dir``). Looks only at the file's metadata, never opens it."""
    import stat

    if root is not None:
        why = link_problem(path, root, follow_symlinks)
        if why:
            return why
    try:
        st = os.stat(path)
    except OSError as exc:
        return f"cannot be read ({exc.strerror or type(exc).__name__})"
    if want_dir:
        return None if stat.S_ISDIR(st.st_mode) else "is not a directory"
    if not stat.S_ISREG(st.st_mode):
        kind = (
            "a FIFO"
            if stat.S_ISFIFO(st.st_mode)
            else "a device"
            if stat.S_ISCHR(st.st_mode) or stat.S_ISBLK(st.st_mode)
            else "a directory"
            if stat.S_ISDIR(st.st_mode)
            else "not a regular file"
        )
        return f"is {kind}, not a regular file: only regular files are read"
    return None


def read_options(path: Path, root: Path | None = None, follow_symlinks: bool = False) -> dict[str, Any]:
    """An options file: a JSON object (at most :data:`MAX_OPTIONS_BYTES`, nested at most
    :data:`MAX_JSON_DEPTH` deep) of known options with usable values (:func:`check_options`);
    :class:`OptionError` naming the file and the problem otherwise. ``root``: the dataset root
    (:func:`file_problem`'s link rule)."""
    why = file_problem(path, root, follow_symlinks)
    if why:
        raise OptionError(f"options file {path}: {why}", E_BAD_PATH)
    try:
        with open(path, "rb") as fh:
            raw = fh.read(MAX_OPTIONS_BYTES + 1)
    except OSError as exc:
        raise OptionError(f"options file {path}: not readable ({exc.strerror or exc})") from None
    if len(raw) > MAX_OPTIONS_BYTES:
        raise OptionError(f"options file {path}: larger than {MAX_OPTIONS_BYTES} bytes")
    try:
        doc = loads_bounded(raw.decode("utf-8"))
    except UnicodeDecodeError:
        raise OptionError(f"options file {path}: not UTF-8 text") from None
    except ValueError as exc:
        raise OptionError(f"options file {path}: not readable JSON ({str(exc)[:120]})") from None
    if not isinstance(doc, dict):
        raise OptionError(f"options file {path}: expected a JSON object")
    return check_options(doc, f"options file {path}")


def default_options() -> dict[str, Any]:
    return {k: d for k, (_, d) in FIELD_OPTIONS.items()}


def _visible(path: Path) -> list[Path]:
    try:
        return sorted((p for p in path.iterdir() if not p.name.startswith((".", "_"))), key=lambda p: p.name)
    except OSError:
        return []


def find_field_recordings(
    root: Path | str, lot: str | None = None, unit: str | None = None, follow_symlinks: bool = False
) -> tuple[list[FieldRecordingRef], list[SessionError]]:
    """Every unit's field recordings under ``root`` (lot and unit names as
    :func:`schemas.dataset.find_sessions` checks them), sorted by lot, unit, rep, and one
    ``E_BAD_PATH`` error per recording directory that is not an IMU-TK pair.

    A recording that cannot be used is still returned, with its ``error`` set (the unit
    fails by name in the night's tables): an options file that is not a bounded JSON object
    of usable values (``E_BAD_OPTION``; ``E_BAD_METADATA`` for ``session_start``), a file
    reached through a symbolic link without ``follow_symlinks`` or outside the dataset root
    with it, a file that is not regular (``E_BAD_PATH``; :func:`file_problem`), a file larger
    than :data:`MAX_RECORDING_BYTES` (``E_UNREADABLE_FILE``). Nothing here opens a file that
    is not a regular file inside the dataset."""
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
            option_files: list[Path] = []
            unit_error: SessionError | None = None
            try:
                for p in (lot_dir / OPTIONS_FILE, fdir / OPTIONS_FILE):
                    if os.path.lexists(p):
                        option_files.append(p)
                        base.update(read_options(p, root, follow_symlinks))
            except OptionError as exc:
                unit_error = _bad(option_files[-1], str(exc), exc.code)
            entries = _visible(fdir)
            names = {p.name for p in entries}
            recordings = [
                p
                for p in entries
                if p.name != OPTIONS_FILE and not (p.suffix == ".json" and (p.name[: -len(".json")] in names))
            ]
            if unit_error is not None and not recordings:
                errors.append(unit_error)
                continue
            for rep, rec in enumerate(recordings, start=1):
                key = SessionKey(lot_id, unit_id, rep)
                error = unit_error
                if rec.is_dir():
                    files = tuple(rec / n for n in IMUTK_PAIR)
                    if not all(os.path.lexists(f) for f in files):
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
                if error is None and os.path.lexists(own):
                    used.append(own)
                    try:
                        opts.update(read_options(own, root, follow_symlinks))
                    except OptionError as exc:
                        error = _bad(own, str(exc), exc.code)
                if error is None:
                    for f in files:
                        why = file_problem(f, root, follow_symlinks)
                        if why:
                            error = SessionError(E_BAD_PATH, str(key), f.name, f"recording {why}")
                            break
                        size = os.stat(f).st_size
                        if size > MAX_RECORDING_BYTES:
                            error = SessionError(
                                E_UNREADABLE_FILE,
                                str(key),
                                f.name,
                                f"recording is {size / 2**20:.0f} MiB, more than a field recording's "
                                f"{MAX_RECORDING_BYTES // 2**20} MiB: not read",
                            )
                            break
                if error is not None and str(key) not in error.session:
                    error = SessionError(error.code, str(key), error.file, error.reason)
                refs.append(FieldRecordingRef(key, rec, files, opts, tuple(used), error))
    refs.sort(key=lambda r: (r.key.lot, r.key.unit, r.key.rep))
    return refs, errors


def field_fingerprint(ref: FieldRecordingRef) -> str:
    """Identity of a recording's content (``xxh3:<32 hex>``, :func:`schemas.hive.fingerprint_of`):
    its file(s) and options files, name, size and digest each (as
    :func:`schemas.dataset.fingerprint` for a session): a changed byte of the log or of an
    option recalibrates the unit."""
    parts = [f"field:{ref.name};"]
    if ref.error is not None:  # a refused file is never opened: its metadata and the reason
        parts.append(f"error:{ref.error};")
    for p in (*ref.files, *ref.option_files):
        try:
            st = os.lstat(p)
            if ref.error is not None or not _regular(p):
                parts.append(f"{p.name}:{st.st_mode}:{st.st_size}:{st.st_mtime_ns};")
            else:
                parts.append(f"{p.name}:{os.stat(p).st_size}:{file_digest(str(p))};")
        except FileNotFoundError:
            parts.append(f"{p.name}:missing;")
    return fingerprint_of("".join(parts))


def _regular(path: Path) -> bool:
    import stat

    try:
        return stat.S_ISREG(os.stat(path).st_mode)
    except OSError:
        return False


def read_field_recording(ref: FieldRecordingRef):
    """The recording as a :class:`schemas.importers.RawRecording` (IMU-TK pair or one
    table). Raises :class:`SessionError` naming the session and the file."""
    from schemas.importers import parse_column_mapping, read_imutk_pair, read_table_recording

    if ref.error is not None:
        raise ref.error
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
