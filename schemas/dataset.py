"""The hive layout ``<root>/lot=<lot>/unit=<unit>/rep=<n>/``: finding sessions and
fingerprinting them, and reading a session's files once for both the fingerprint and the
reader (:func:`read_session_files`).

Bad directory names never raise: each becomes an ``E_BAD_PATH`` :class:`SessionError` in the
returned list, and the rest of the fleet is still found. Entries whose name starts with ``.``
or ``_`` (temp and hidden directories, as pyarrow's dataset discovery treats them) and plain
files (``fleet.json``) are ignored.
"""

from __future__ import annotations

import os
import stat
from dataclasses import dataclass
from pathlib import Path
from typing import ClassVar

from calib_core.steps import SessionKey
from schemas.contract import SAMPLES_FILE, STEPS_FILE
from schemas.errors import E_BAD_PATH, SessionError
from schemas.hive import (  # noqa: F401  (the id rule re-exported: callers check ids here)
    DIGEST_SCHEME,
    FIELD_DIR,
    ID_PATTERN,
    ID_RULE,
    NOISE_DIR,
    REP_PATTERN,
    bytes_digest,
    check_id,
    file_digest,
    fingerprint_of,
    id_problem,
    link_problem,
    read_regular_file,
)
from schemas.hive import bad_path as _bad
from schemas.hive import parse_part as _parse_part
from schemas.hive import visible_dirs as _visible_dirs
from schemas.noise_dataset import noise_fingerprint


@dataclass(frozen=True)
class SessionRef:
    """A session directory and its parsed identity."""

    key: SessionKey
    path: Path
    kind: ClassVar[str] = "turntable"  # the unit pipeline that calibrates it (flows.unit_pipeline)

    def content_fingerprint(self, cache=None) -> str:
        """:func:`fingerprint` of the session directory."""
        return fingerprint(self.path, cache)

    @property
    def steps_path(self) -> Path:
        return self.path / STEPS_FILE

    @property
    def samples_path(self) -> Path:
        return self.path / SAMPLES_FILE

    def __str__(self) -> str:
        return str(self.key)


def session_dir(root: Path | str, key: SessionKey) -> Path:
    return Path(root) / f"lot={key.lot}" / f"unit={key.unit}" / f"rep={key.rep}"


def find_sessions(
    root: Path | str, lot: str | None = None, unit: str | None = None, follow_symlinks: bool = False
) -> tuple[list[SessionRef], list[SessionError]]:
    """All sessions under ``root`` (optionally of one lot and/or unit), sorted by lot, unit,
    rep, and one E_BAD_PATH error per directory that does not parse or per session of a unit
    found in more than one lot. A missing root is an E_BAD_PATH error too.

    A session reached through a symbolic link (its lot, unit or rep directory, or one of its
    files) follows the dataset's link rule (:func:`schemas.hive.link_problem`): an E_BAD_PATH
    error without ``follow_symlinks``, and with it too when the link leads outside the dataset
    root; a followed directory link is recorded with its resolved path."""
    root = Path(root)
    errors: list[SessionError] = []
    if not root.is_dir():
        return [], [_bad(root, f"dataset root {str(root)!r} is not a directory")]
    refs: list[SessionRef] = []
    for lot_dir in _visible_dirs(root):
        lot_id, why = _parse_part(lot_dir.name, "lot")
        if why:
            errors.append(_bad(lot_dir, why))
            continue
        if lot is not None and lot_id != lot:
            continue
        for unit_dir in _visible_dirs(lot_dir):
            unit_id, why = _parse_part(unit_dir.name, "unit")
            if why:
                errors.append(_bad(unit_dir, why))
                continue
            if unit is not None and unit_id != unit:
                continue
            for rep_dir in _visible_dirs(unit_dir):
                if rep_dir.name in (FIELD_DIR, NOISE_DIR):  # schemas.field_dataset, .noise_dataset
                    continue
                rep, why = _parse_part(rep_dir.name, "rep")
                if why:
                    errors.append(_bad(rep_dir, why))
                    continue
                path = rep_dir
                why = link_problem(rep_dir / SAMPLES_FILE, root, follow_symlinks) or link_problem(
                    rep_dir / STEPS_FILE, root, follow_symlinks
                )
                if why:
                    errors.append(_bad(rep_dir, why))
                    continue
                if lot_dir.is_symlink() or unit_dir.is_symlink() or rep_dir.is_symlink():
                    path = rep_dir.resolve()
                refs.append(SessionRef(SessionKey(lot_id, unit_id, int(rep)), path))
    # a unit belongs to one lot: when it is found under several, none of its sessions is used
    # (which lot is right is not ours to guess). With a lot filter the other lots were not
    # walked, so look for the unit's directories in them directly.
    lots_of: dict[str, set[str]] = {}
    for ref in refs:
        lots_of.setdefault(ref.key.unit, set()).add(ref.key.lot)
    if lot is not None:
        for lot_dir in _visible_dirs(root):
            other, why = _parse_part(lot_dir.name, "lot")
            if why or other == lot:
                continue
            for u in lots_of:
                if (lot_dir / f"unit={u}").is_dir():
                    lots_of[u].add(other)
    ambiguous = {u: sorted(ls) for u, ls in lots_of.items() if len(ls) > 1}
    kept = []
    for ref in refs:
        if ref.key.unit in ambiguous:
            errors.append(
                SessionError(
                    E_BAD_PATH,
                    str(ref.key),
                    ref.path.name,
                    f"unit {ref.key.unit!r} appears in lots {', '.join(ambiguous[ref.key.unit])}; "
                    f"a unit belongs to one lot",
                )
            )
        else:
            kept.append(ref)
    kept.sort(key=lambda r: (r.key.lot, r.key.unit, r.key.rep))
    return kept, errors


def count_unit_dirs(root: Path | str) -> int:
    """How many ``lot=*/unit=*`` directories are under ``root`` (no session is looked at, no
    name checked): a quick upper bound on the units a run may calibrate, for deciding before
    the run whether to prepare worker processes."""
    return sum(
        len(_visible_dirs(lot_dir))
        for lot_dir in _visible_dirs(Path(root))
        if lot_dir.name.startswith("lot=")
    )


class DigestCache:
    """File digests keyed by the file's (size, mtime_ns, ctime_ns, inode): a file whose stat
    is unchanged is not read again. Any write changes ctime (which no tool can set back), so
    an entry is only reused for the very bytes it was computed from; a copy (new inode) is
    read once and gives the same digest. ``entries``: path -> [size, mtime_ns, ctime_ns,
    inode, digest, scheme], JSON-ready (the nightly flow keeps it in the results store); an
    entry of another digest scheme (or of none: the earlier five-item entries) is computed
    again."""

    def __init__(self, entries: dict | None = None) -> None:
        self.entries: dict[str, list] = dict(entries or {})
        self.read = 0

    def digest(self, path: str) -> str:
        st = os.stat(path)
        key = [st.st_size, st.st_mtime_ns, st.st_ctime_ns, st.st_ino]
        e = self.entries.get(path)
        if isinstance(e, list) and len(e) == 6 and e[:4] == key and e[5] == DIGEST_SCHEME:
            return str(e[4])
        d = file_digest(path)
        self.read += 1
        self.entries[path] = key + [d, DIGEST_SCHEME]
        return d


_SESSION_FILES = (STEPS_FILE, SAMPLES_FILE)


def _file_part(name: str, size: int | None, digest: str | None) -> str:
    """A file's entry in a session's fingerprint (None: the file is missing)."""
    return f"{name}:missing;" if digest is None else f"{name}:{size}:{digest};"


def _session_fingerprint(path: str, file_parts: list[str], cache: DigestCache | None) -> str:
    parts = "".join(file_parts)
    # the unit's noise recordings (schemas.noise_dataset): a unit without them has none
    noise = noise_fingerprint(os.path.dirname(os.path.abspath(path)), cache)
    if noise is not None:
        parts += f"noise:{noise};"
    return fingerprint_of(parts)


def fingerprint(path: Path | str, cache: DigestCache | None = None) -> str:
    """Identity of a session's content (``xxh3:<32 hex>``, :func:`schemas.hive.fingerprint_of`):
    size and digest of both files and of the unit's noise recordings. A copy of the dataset,
    a ``touch`` or a rewrite with the same bytes keep it; any changed byte changes it.
    ``cache`` saves reading files whose stat is unchanged (:class:`DigestCache`). The same
    fingerprint as :func:`read_session_files` gives of the same bytes."""
    base = os.fspath(path)
    file_parts = []
    for name in _SESSION_FILES:
        p = os.path.join(base, name)
        try:
            d = cache.digest(p) if cache is not None else file_digest(p)
            file_parts.append(_file_part(name, os.stat(p).st_size, d))
        except FileNotFoundError:
            file_parts.append(_file_part(name, None, None))
    return _session_fingerprint(base, file_parts, cache)


@dataclass(frozen=True)
class SessionFiles:
    """A session's two files read once: the bytes of each regular file (None for a file
    missing, empty, not regular or unreadable: the reader then opens it by its path and
    reports why) and the :func:`fingerprint` of those very bytes ("" when a file could not be
    read: the unit then counts as changed on the next run)."""

    steps: bytes | None
    samples: bytes | None
    fingerprint: str


# A session file larger than this is not held in memory whole: it is hashed in chunks and the
# reader reads only the contract's columns from it by its path (two reads, as before the one
# read; a 6-minute session at 100 Hz is ~0.8 MB, an hour at 1 kHz ~100 MB). A file with a huge
# extra column then costs no more memory than its contract columns.
MAX_HELD_BYTES = 256 * 1024 * 1024


def read_session_files(path: Path | str) -> SessionFiles:
    """Both files of the session directory ``path``, each read whole in one call (FIFOs and
    devices never opened: :func:`schemas.hive.read_regular_file`; files over
    :data:`MAX_HELD_BYTES` hashed in chunks, not held), with their fingerprint. Never raises
    on a bad session."""
    base = os.fspath(path)
    content: list[bytes | None] = []
    file_parts = []
    failed = False
    for name in _SESSION_FILES:
        p = os.path.join(base, name)
        try:
            raw, st = read_regular_file(p, MAX_HELD_BYTES)
            if raw is not None:
                part = _file_part(name, len(raw), bytes_digest(raw))
            elif stat.S_ISREG(st.st_mode):  # too large to hold
                part = _file_part(name, os.stat(p).st_size, file_digest(p))
            else:
                part = _file_part(name, st.st_size, f"not-a-regular-file:{st.st_mode:o}")
        except FileNotFoundError:
            raw, part = None, _file_part(name, None, None)
        except (OSError, ValueError):
            raw, part, failed = None, "", True
        content.append(raw or None)
        file_parts.append(part)
    fp = ""
    if not failed:
        try:
            fp = _session_fingerprint(base, file_parts, None)
        except OSError:
            fp = ""
    return SessionFiles(content[0], content[1], fp)
