"""flows.memory.release_memory: freed heap pages go back to the OS (glibc)."""

from __future__ import annotations

import numpy as np
import pytest

from flows.memory import _malloc_trim, release_memory


def _rss_mb() -> float:
    with open("/proc/self/statm") as fh:
        return int(fh.read().split()[1]) * 4096 / 2**20


@pytest.mark.skipif(_malloc_trim() is None, reason="not glibc")
def test_release_memory_returns_freed_holes_of_the_heap():
    release_memory()
    # 6,000 blocks of 32 KB (below the mmap threshold: from the heap), every other one freed:
    # ~94 MB of holes that malloc keeps resident, none at the top of the heap
    blocks = [np.ones(4096) for _ in range(6_000)]
    keep = blocks[1::2]
    del blocks
    before = _rss_mb()
    release_memory()
    after = _rss_mb()
    assert len(keep) == 3_000
    assert before - after > 60  # most of the ~94 MB of holes
