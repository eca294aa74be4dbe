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
"""

from __future__ import annotations

import ctypes
import ctypes.util
import gc
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
