"""A unit's long static recordings in the dataset: the data its noise model is measured on.

Layout (an optional addition beside the contract's ``rep=<n>`` sessions; a dataset without
it is read as before)::

    <root>/lot=<lot>/unit=<unit>/noise/<name>.parquet

Each file has the columns of ``samples.parquet`` (``t``, ``gx gy gz ax ay az``, optional
``temp_c``; a ``step`` column may be there and is not read) and its key-value metadata
(``gyro_unit``, ``accel_unit``, ranges; ``sample_rate_hz`` optional), recorded with the unit
at rest, uniformly sampled (docs/data-contract.md). ``<name>`` follows the id rule of lots
and units. Names starting with ``.`` or ``_`` are ignored.

Hostile input, as for sessions: a recording or a ``noise`` directory reached through a
symbolic link is refused unless ``follow_symlinks``; only regular files are opened (a FIFO
or a device is refused by its type, never opened); every problem is one
:class:`SessionError` naming ``lot=L/unit=U/noise/<name>``, the file and the reason.
:func:`find_noise_recordings` never raises; :func:`read_noise_recording` raises
:class:`SessionError`.
"""

from __future__ import annotations

import os
import stat
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pyarrow.parquet as pq

from schemas.contract import SENSOR_COLUMNS, ColumnRule, SessionMeta, _is_float, check_columns, parse_metadata
from schemas.errors import (
    E_BAD_PATH,
    E_EMPTY_SESSION,
    E_NONFINITE_VALUE,
    E_NONINCREASING_TIME,
    E_UNREADABLE_FILE,
    SessionError,
)
from schemas.hive import NOISE_DIR, file_digest, id_problem

NOISE_SUFFIX = ".parquet"
# fewer samples cannot give an Allan deviation over more than a few cluster sizes
MIN_NOISE_SAMPLES = 256
# a step of t larger than this many median steps is a gap: the Allan variance assumes a
# uniformly sampled record
MAX_GAP_STEPS = 1.5

NOISE_RULES = (
    ColumnRule("t", _is_float, "float64"),
    *(ColumnRule(c, _is_float, "float32 or float64") for c in SENSOR_COLUMNS),
    ColumnRule("temp_c", _is_float, "float32", required=False),
)


@dataclass(frozen=True)
class NoiseRecordingRef:
    """One noise recording of a unit: ``lot=L/unit=U/noise/<name>``."""

    lot: str
    unit: str
    name: str
    path: Path

    @property
    def label(self) -> str:
        return f"lot={self.lot}/unit={self.unit}/{NOISE_DIR}/{self.name}"

    def __str__(self) -> str:
        return self.label


@dataclass
class NoiseRecording:
    """A validated noise recording: time (s), gyro (n, 3) in deg/s or raw, accel (n, 3) in
    g or raw (the session reader's conversions), its sample rate and metadata."""

    ref: NoiseRecordingRef | None  # None: a file read outside a dataset (``mimucal noise``)
    t: np.ndarray
    gyro: np.ndarray
    accel: np.ndarray
    rate_hz: float
    meta: SessionMeta

    @property
    def duration_s(self) -> float:
        return float(len(self.t) / self.rate_hz)


def _bad(label: str, path: Path, reason: str) -> SessionError:
    return SessionError(E_BAD_PATH, label, path.name, reason)


def find_noise_recordings(
    unit_dir: Path | str, lot: str, unit: str, follow_symlinks: bool = False
) -> tuple[list[NoiseRecordingRef], list[SessionError]]:
    """The noise recordings of one unit directory, by name, and one error per entry of its
    ``noise/`` directory that cannot be one (never raises). No ``noise/``: nothing."""
    ndir = Path(unit_dir) / NOISE_DIR
    label = f"lot={lot}/unit={unit}/{NOISE_DIR}"
    try:
        st = os.lstat(ndir)
    except OSError:
        return [], []
    if stat.S_ISLNK(st.st_mode) and not follow_symlinks:
        return [], [
            _bad(
                label,
                ndir,
                f"{ndir} is a symbolic link; pass --follow-symlinks to read recordings through it",
            )
        ]
    if not ndir.is_dir():
        return [], [
            _bad(label, ndir, f"{ndir} is not a directory (noise recordings are noise/<name>.parquet)")
        ]
    refs, errors = [], []
    try:
        entries = sorted(ndir.iterdir(), key=lambda p: p.name)
    except OSError as exc:
        return [], [_bad(label, ndir, f"cannot list {ndir}: {exc.strerror}")]
    for p in entries:
        if p.name.startswith((".", "_")):
            continue
        name = p.name[: -len(NOISE_SUFFIX)] if p.name.endswith(NOISE_SUFFIX) else p.name
        where = f"{label}/{name}"
        if not p.name.endswith(NOISE_SUFFIX):
            errors.append(
                _bad(where, p, f"{p.name!r} is not a noise recording: expected <name>{NOISE_SUFFIX}")
            )
            continue
        why = id_problem(name, "recording")
        if why:
            errors.append(_bad(where, p, why))
            continue
        try:
            lst = os.lstat(p)
        except OSError as exc:
            errors.append(_bad(where, p, f"cannot stat {p}: {exc.strerror}"))
            continue
        if stat.S_ISLNK(lst.st_mode) and not follow_symlinks:
            errors.append(_bad(where, p, f"{p} is a symbolic link; pass --follow-symlinks to read it"))
            continue
        try:
            mode = os.stat(p).st_mode
        except OSError as exc:
            errors.append(_bad(where, p, f"cannot stat {p}: {exc.strerror}"))
            continue
        if not stat.S_ISREG(mode):
            errors.append(SessionError(E_UNREADABLE_FILE, where, p.name, f"{p} is not a regular file"))
            continue
        refs.append(NoiseRecordingRef(lot, unit, name, p))
    return refs, errors


def noise_fingerprint(unit_dir: Path | str, cache=None) -> str | None:
    """The digests of a unit's noise recordings (None: the unit has none), so that adding or
    changing one makes the unit's sessions 'changed' for the nightly. ``cache``: a
    :class:`schemas.dataset.DigestCache`."""
    ndir = Path(unit_dir) / NOISE_DIR
    if not ndir.is_dir():
        return None
    parts = []
    for p in sorted(ndir.iterdir(), key=lambda p: p.name):
        if p.name.startswith((".", "_")):
            continue
        try:
            d = cache.digest(str(p)) if cache is not None else file_digest(str(p))
            parts.append(f"{p.name}:{d}")
        except OSError:
            parts.append(f"{p.name}:unreadable")
    return ";".join(parts)


def read_noise_recording(ref: NoiseRecordingRef) -> NoiseRecording:
    """Open, check and convert one noise recording of the dataset (:func:`read_static_parquet`).
    Raises :class:`SessionError`."""
    return read_static_parquet(ref.path, ref.label, ref)


def read_static_parquet(path: Path, label: str, ref: NoiseRecordingRef | None = None) -> NoiseRecording:
    """Open, check and convert one static Parquet recording with the contract's columns and
    metadata: a regular file, at least ``MIN_NOISE_SAMPLES`` finite samples, uniformly
    sampled, with the session reader's unit conversions (rad/s -> deg/s, m/s^2 -> g of its
    ``g_local``; raw counts stay counts). The one reader of the fleet's noise recordings and
    of ``mimucal noise``'s Parquet input. Raises :class:`SessionError` naming ``label``."""
    path = Path(path)
    file = path.name
    try:
        st = os.stat(path)
    except OSError as exc:
        raise SessionError(E_UNREADABLE_FILE, label, file, f"cannot open {path}: {exc.strerror}") from None
    if not stat.S_ISREG(st.st_mode):
        raise SessionError(E_UNREADABLE_FILE, label, file, f"{path} is not a regular file")
    if st.st_size == 0:
        raise SessionError(E_UNREADABLE_FILE, label, file, "file is empty (0 bytes)")
    try:
        pf = pq.ParquetFile(path, page_checksum_verification=True)
        schema = pf.schema_arrow
    except Exception as exc:  # noqa: BLE001 - any decoding failure is the file's
        raise SessionError(
            E_UNREADABLE_FILE, label, file, f"not a readable Parquet file (truncated or corrupt?): {exc}"
        ) from None
    meta = parse_metadata(schema.metadata, label, file)
    names = check_columns(schema, NOISE_RULES, label, file)
    try:
        table = pf.read(columns=names)
    except Exception as exc:  # noqa: BLE001
        raise SessionError(E_UNREADABLE_FILE, label, file, f"Parquet data cannot be decoded: {exc}") from None
    n = table.num_rows
    if n < MIN_NOISE_SAMPLES:
        raise SessionError(
            E_EMPTY_SESSION, label, file, f"{n} samples; a noise recording needs at least {MIN_NOISE_SAMPLES}"
        )
    t = table.column("t").to_numpy(zero_copy_only=False).astype(float)
    if not np.isfinite(t).all():
        i = int(np.flatnonzero(~np.isfinite(t))[0])
        raise SessionError(E_NONFINITE_VALUE, label, file, f"time is not finite at row {i}", column="t")
    dt = np.diff(t)
    if (dt <= 0).any():
        i = int(np.flatnonzero(dt <= 0)[0]) + 1
        raise SessionError(
            E_NONINCREASING_TIME, label, file, f"t is not strictly increasing at row {i}", column="t"
        )
    step = float(np.median(dt))
    gaps = np.flatnonzero(dt > MAX_GAP_STEPS * step)
    if len(gaps):
        i = int(gaps[0])
        raise SessionError(
            E_NONINCREASING_TIME,
            label,
            file,
            f"not uniformly sampled: a gap of {dt[i]:.6g} s after t={t[i]:.6g} s (median step "
            f"{step:.6g} s, {len(gaps)} gap(s)); the Allan variance needs an unbroken record",
            column="t",
        )
    channels = np.empty((6, n))
    for j, c in enumerate(SENSOR_COLUMNS):
        channels[j] = table.column(c).to_numpy(zero_copy_only=False)
    finite = np.isfinite(channels)
    if not finite.all():
        j, i = (int(x[0]) for x in np.nonzero(~finite))
        raise SessionError(
            E_NONFINITE_VALUE,
            label,
            file,
            f"{SENSOR_COLUMNS[j]} is not finite at row {i} ({int((~finite).sum())} value(s))",
            column=SENSOR_COLUMNS[j],
        )
    channels[:3] *= meta.gyro_scale
    channels[3:] *= meta.accel_scale
    rate = meta.sample_rate_hz or 1.0 / step
    return NoiseRecording(ref, t, channels[:3].T.copy(), channels[3:].T.copy(), float(rate), meta)
