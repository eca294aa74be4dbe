"""The hive layout's shared pieces: lot, unit and rep directory names (``lot=<id>``), the id
rule, the unit a path names, and the one content digest of files and fingerprints.
``schemas.dataset`` (turntable sessions) and ``schemas.field_dataset`` (field recordings) both
build on it; neither imports the other's helpers."""

from __future__ import annotations

import os
import re
import stat
from pathlib import Path

import xxhash

from schemas.errors import E_BAD_PATH, SessionError

FIELD_DIR = "field"  # the directory of a unit's field recordings
NOISE_DIR = "noise"  # a unit's long static recordings (schemas.noise_dataset)

# Lot and unit ids are directory and file names in the results store (calibrations/<unit>/,
# reports/units/<unit>.html): full-string matches (\A...\Z: a trailing newline does not pass,
# as it would with ``$``), a letter or digit first (no ``.``, ``..``, hidden or option-like
# names), no ``.`` last (dropped by some file systems), at most 128 characters, and none of
# the names Windows reserves. Control characters, separators and spaces never match.
ID_RULE = "[A-Za-z0-9][A-Za-z0-9_.-]* (at most 128 characters, not ending with '.')"
ID_PATTERN = re.compile(r"\A[A-Za-z0-9](?:[A-Za-z0-9_.-]{0,126}[A-Za-z0-9_-])?\Z")
REP_PATTERN = re.compile(r"\A[1-9][0-9]{0,8}\Z")
_RESERVED_NAMES = frozenset(
    {"CON", "PRN", "AUX", "NUL", *(f"COM{i}" for i in range(1, 10)), *(f"LPT{i}" for i in range(1, 10))}
)


def id_problem(value: str, field: str) -> str | None:
    """Why ``value`` is not a valid ``field`` (lot/unit) id, or None when it is."""
    if not isinstance(value, str) or not ID_PATTERN.match(value):
        return f"{field} id {value!r} must match {ID_RULE}"
    if value.split(".")[0].upper() in _RESERVED_NAMES:
        return f"{field} id {value!r} is a name the file system reserves"
    return None


def check_id(value: str, field: str) -> str:
    """``value`` when it is a valid lot/unit id; ValueError naming the rule otherwise (the
    check every ``--lot``/``--unit`` argument goes through, as directory names do)."""
    why = id_problem(value, field)
    if why:
        raise ValueError(why)
    return value


def visible_dirs(path: Path) -> list[Path]:
    """The sub-directories of ``path`` by name, hidden and temp ones (``.``, ``_``) left out."""
    try:
        entries = sorted(path.iterdir(), key=lambda p: p.name)
    except OSError:
        return []
    return [p for p in entries if p.is_dir() and not p.name.startswith((".", "_"))]


def parse_part(name: str, field: str) -> tuple[str | None, str | None]:
    """``lot=L01`` -> ("L01", None); a bad name -> (None, reason)."""
    prefix = f"{field}="
    if not name.startswith(prefix):
        return None, f"directory name {name!r} does not parse: expected '{prefix}<id>'"
    value = name[len(prefix) :]
    if field == "rep":
        if not REP_PATTERN.match(value):
            return None, (
                f"directory name {name!r} does not parse: rep must be an integer >= 1 without leading zeros"
            )
        return value, None
    why = id_problem(value, field)
    if why:
        return None, f"directory name {name!r} does not parse: {why}"
    return value, None


def bad_path(path: Path, reason: str, code: str = E_BAD_PATH) -> SessionError:
    """The error (``E_BAD_PATH`` unless ``code`` says otherwise) of a directory or file that
    does not fit the layout or cannot be used."""
    return SessionError(code, str(path), path.name, reason)


def hive_keys(path: Path | str) -> dict[str, str]:
    """The ``key=value`` directory names of a path, e.g. ``{"lot": "L01", "unit": "U0002",
    "rep": "1"}`` of ``data/lot=L01/unit=U0002/rep=1/samples.parquet`` (the innermost wins);
    names that do not parse as the layout's are left out."""
    out: dict[str, str] = {}
    for part in Path(path).parts:
        key, sep, value = part.partition("=")
        if sep and key in ("lot", "unit", "rep"):
            got, why = parse_part(part, key)
            if why is None and got is not None:
                out[key] = got
    return out


def link_problem(path: Path, root: Path, follow_symlinks: bool) -> str | None:
    """The dataset's one link rule, for turntable sessions and field files alike: why
    ``path`` (below the dataset ``root``) must not be read because of a symbolic link on its
    way down from ``root``, or None. Without ``follow_symlinks`` any link is refused; with
    it, a link is followed only when everything it leads to stays inside ``root``. Looks
    only at metadata, never opens the file."""
    try:
        rel = path.relative_to(root)
    except ValueError:
        return None
    cur = root
    link = None
    for part in rel.parts:
        cur = cur / part
        if cur.is_symlink():
            link = cur
            break
    if link is None:
        return None
    try:
        target = link.resolve()
        real_path = path.resolve()
        real_root = root.resolve()
    except (OSError, RuntimeError):  # a link loop
        return f"{link.name} is a symbolic link that does not resolve (a loop?)"
    if not follow_symlinks:
        return (
            f"{link.name} is a symbolic link (to {target}); dataset files are not read "
            "through links: pass --follow-symlinks to read links inside the dataset"
        )
    if not real_path.is_relative_to(real_root):
        return f"{link.name} is a symbolic link to {target}, outside the dataset root {real_root}"
    return None


# The one content digest of the files a run fingerprints (turntable sessions, field
# recordings, noise recordings) and of the fingerprints made of them: xxHash's XXH3, 128 bit.
# A fingerprint tells whether the bytes calibrated last time are still those on disk; it is
# no security boundary (whoever can write the dataset decides what is calibrated anyway), so
# a fast non-cryptographic hash is enough. Fingerprints carry the scheme as a prefix
# (``xxh3:<32 hex>``); those of the earlier scheme (blake2b files under a sha256, 32 bare hex
# digits) are recognised (:func:`fingerprint_scheme`) and their units recalibrated once.
DIGEST_SCHEME = "xxh3"
_LEGACY_FINGERPRINT = re.compile(r"\A[0-9a-f]{32}\Z")
_CHUNK = 1 << 20


def bytes_digest(data) -> str:
    """The content digest (32 hex digits) of ``data`` (bytes or any buffer)."""
    return xxhash.xxh3_128_hexdigest(data)


def file_digest(path: str) -> str:
    """:func:`bytes_digest` of a file's bytes, read in chunks into one buffer; a FIFO or a
    device is never opened (its type stands for its content: the reader refuses it)."""
    mode = os.stat(path).st_mode
    if not stat.S_ISREG(mode):
        return f"not-a-regular-file:{mode:o}"
    h = xxhash.xxh3_128()
    buf = bytearray(_CHUNK)
    view = memoryview(buf)
    with open(path, "rb", buffering=0) as fh:
        while n := fh.readinto(buf):
            h.update(view[:n])
    return h.hexdigest()


def read_regular_file(path: str, max_bytes: int | None = None) -> tuple[bytes | None, os.stat_result]:
    """(the bytes, the stat) of a regular file, read whole in one call; (None, stat) of
    anything else, which is never read: a FIFO or a device is not opened at all, and one that
    replaces the file between the stat and the open is opened without blocking and closed
    unread. ``max_bytes``: a larger file is not read either (nor kept when it grew past it
    while read). FileNotFoundError when ``path`` is missing; other OSErrors as raised."""
    st = os.stat(path)
    if not stat.S_ISREG(st.st_mode) or (max_bytes is not None and st.st_size > max_bytes):
        return None, st
    fd = os.open(path, os.O_RDONLY | os.O_NONBLOCK | os.O_CLOEXEC)
    with open(fd, "rb", buffering=0) as fh:
        st = os.fstat(fd)
        if not stat.S_ISREG(st.st_mode) or (max_bytes is not None and st.st_size > max_bytes):
            return None, st
        data = fh.readall()
    return (None if max_bytes is not None and len(data) > max_bytes else data), st


def fingerprint_of(parts: str) -> str:
    """A fingerprint (``xxh3:<32 hex>``) of the text that lists a reference's files and
    their digests."""
    return f"{DIGEST_SCHEME}:{bytes_digest(parts.encode())}"


def fingerprint_scheme(fp: str | None) -> str | None:
    """The scheme of a stored fingerprint: :data:`DIGEST_SCHEME` for the current one,
    ``"blake2b"`` for the earlier one (32 bare hex digits), None for anything else (no
    fingerprint, an unreadable session's empty one)."""
    if not isinstance(fp, str):
        return None
    if fp.startswith(DIGEST_SCHEME + ":"):
        return DIGEST_SCHEME
    if _LEGACY_FINGERPRINT.match(fp):
        return "blake2b"
    return None
