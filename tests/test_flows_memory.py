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


_FAULTS = """
import resource, sys
import numpy as np
if sys.argv[1] == "keep":
    from flows.memory import keep_freed_memory
    keep_freed_memory()
a = np.ones(1 << 17)  # 1 MB, as discovery's step arrays
before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
for _ in range(200):
    b = [a * k for k in range(8)]  # eight fresh 1 MB arrays, all freed at the next pass
after = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
print(after - before)
"""


@pytest.mark.skipif(_malloc_trim() is None, reason="not glibc")
def test_keep_freed_memory_stops_the_page_faults_of_freed_arrays():
    """Arrays of 1 MB freed together and allocated again: glibc's default gives the freed
    heap top back (above its trim threshold) and the next ones fault every page in again;
    once keep_freed_memory ran, the heap keeps and serves them."""
    import os
    import subprocess
    import sys
    from pathlib import Path

    env = {k: v for k, v in os.environ.items() if not k.startswith(("MALLOC_", "GLIBC_TUNABLES"))}
    env["PYTHONPATH"] = str(Path(__file__).resolve().parents[1])

    def faults(mode: str) -> int:
        out = subprocess.run([sys.executable, "-c", _FAULTS, mode], capture_output=True, text=True, env=env)
        assert out.returncode == 0, out.stderr
        return int(out.stdout.strip())

    default, kept = faults("default"), faults("keep")
    assert default > 200 * 256  # ~2,000 pages a pass
    assert kept < default / 20
