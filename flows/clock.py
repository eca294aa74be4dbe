"""Wall time since the command started: from the process's start (Linux /proc), so that a
command's reported time includes its imports and Prefect's start-up, not only its flow."""

from __future__ import annotations

import os
import time

_IMPORTED = time.monotonic()


def _process_age() -> float | None:
    """Seconds since this process started, from /proc (None elsewhere)."""
    try:
        with open("/proc/self/stat") as fh:
            stat = fh.read()
        start_ticks = int(stat.rsplit(")", 1)[1].split()[19])  # field 22: starttime
        with open("/proc/uptime") as fh:
            uptime = float(fh.read().split()[0])
        return max(0.0, uptime - start_ticks / os.sysconf("SC_CLK_TCK"))
    except (OSError, ValueError, IndexError):
        return None


_AGE_AT_IMPORT = _process_age()


def since_start() -> float:
    """Wall seconds since the process started (since this module's import where /proc is
    missing)."""
    base = _AGE_AT_IMPORT if _AGE_AT_IMPORT is not None else 0.0
    return base + (time.monotonic() - _IMPORTED)
