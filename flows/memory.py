"""Give memory the process has freed back to the operating system.

Why (docs/benchmarks.md): the nightly flow's process works lot by lot (store a lot, later
write a lot report), and each lot's work allocates ~50-100 MB that is freed when the lot is
done. glibc's malloc keeps freed chunks in its arenas (one per thread that allocated: the
flow's thread, the store's writer thread, the task runner's threads) and returns them to the
OS only from the top of a heap; pyarrow's mimalloc pool keeps freed pages for reuse. The next
lot's allocations do not fit the holes exactly, so the resident size ratcheted up by a few MB
per lot (nightly at 200 units: 577 -> 612 -> 621 -> 631 MB over the four lot reports) while
the live data stayed flat. ``malloc_trim(0)`` releases the free pages inside every arena
(``MADV_DONTNEED``), ``release_unused`` those of Arrow's pool: called between lots, the
peak no longer depends on how many lots came before.

The other way round, within a unit's work (:func:`keep_freed_memory`): model discovery
allocates and frees arrays of about 1 MB at every step, above glibc's default mmap
threshold, so each was handed back to the OS and page-faulted afresh by the next.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import gc
import os
import sys
from functools import lru_cache


@lru_cache(maxsize=1)
def _malloc_trim():
    """glibc's ``malloc_trim``, or None (another libc: nothing to do)."""
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
        trim = libc.malloc_trim
    except (OSError, AttributeError):
        return None
    trim.argtypes = [ctypes.c_size_t]
    trim.restype = ctypes.c_int
    return trim


def release_memory() -> None:
    """Return freed heap pages (all malloc arenas) and Arrow's unused pool memory to the OS.
    A full garbage collection first: the results of a lot hold reference cycles that wait
    for a generation-2 collection otherwise. Costs ~0.1-0.2 s; call it between lots, not per
    unit."""
    gc.collect()
    try:
        import pyarrow as pa

        pa.default_memory_pool().release_unused()
    except Exception:  # pragma: no cover - a pool without the call
        pass
    trim = _malloc_trim()
    if trim is not None:
        trim(0)


_M_TRIM_THRESHOLD, _M_MMAP_THRESHOLD = -1, -3  # glibc's malloc.h


@lru_cache(maxsize=1)
def keep_freed_memory() -> None:
    """Once per process (the unit pipeline's first batch): glibc serves blocks up to 32 MB
    from its heap and keeps up to 64 MB of the heap's free top, instead of unmapping each
    ~1 MB array discovery frees and faulting the next one in afresh (docs/benchmarks.md has
    the figures). :func:`release_memory` still trims between lots. Not on other C libraries,
    nor when the environment sets glibc's malloc itself."""
    if not sys.platform.startswith("linux") or any(
        k in os.environ for k in ("MALLOC_MMAP_THRESHOLD_", "MALLOC_TRIM_THRESHOLD_", "GLIBC_TUNABLES")
    ):
        return
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
        libc.gnu_get_libc_version  # noqa: B018 - glibc only (AttributeError elsewhere)
        libc.mallopt(_M_MMAP_THRESHOLD, 32 << 20)
        libc.mallopt(_M_TRIM_THRESHOLD, 64 << 20)
    except (OSError, AttributeError):  # pragma: no cover - not glibc
        return
