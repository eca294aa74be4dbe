"""Which of a field unit's recordings model discovery looks at: the one with the most static
poses (the static engine's design grows with them), and only when it has enough poses for the
base parameters and some degrees of freedom."""

from __future__ import annotations

from collections.abc import Sequence

MIN_DISCOVERY_POSES = 12  # 9 accel + 3 gyro base parameters and some degrees of freedom


def recording_for_discovery(pose_counts: Sequence[int]) -> tuple[int | None, str | None]:
    """(index of the recording to diagnose, None) or (None, why discovery is skipped); the
    first of equal counts is chosen. ``pose_counts``: static poses of each fitted recording."""
    if not len(pose_counts):
        return None, "model discovery skipped: no recording was fitted"
    best = max(range(len(pose_counts)), key=lambda i: pose_counts[i])
    if pose_counts[best] < MIN_DISCOVERY_POSES:
        return None, f"model discovery skipped: {pose_counts[best]} static poses, needs {MIN_DISCOVERY_POSES}"
    return best, None
