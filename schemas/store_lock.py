"""The store's lock: ``.lock``, held (flock) by the run writing the store; a second run is
refused naming the holder, or waits. Taking it removes the temp files of writers that died."""

from __future__ import annotations

import errno
import fcntl
import json
import os
import socket
import stat
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

from schemas.store_io import StoreError, iso, utc_now


class StoreLockedError(RuntimeError):
    """Another run holds the results root."""


def stat_is_regular(fd: int) -> bool:
    return stat.S_ISREG(os.fstat(fd).st_mode)


class StoreLock:
    """The lock of the store rooted at ``self.root``."""

    root: Path
    runs_dir: Path
    calibrations_dir: Path
    tables_dir: Path

    @property
    def lock_path(self) -> Path:
        return self.root / ".lock"

    @contextmanager
    def lock(
        self, owner: str, wait: bool = False, timeout: float | None = None, poll_s: float = 0.5
    ) -> Iterator[None]:
        """Hold the results root for one run. ``flock`` is released by the kernel if the
        process dies, so a crashed run never leaves the store locked. A second run is refused
        with :class:`StoreLockedError` naming the holder, or waits (``wait=True``)."""
        self.root.mkdir(parents=True, exist_ok=True)
        try:  # never through a symbolic link: it would truncate the file it points to
            fd = os.open(self.lock_path, os.O_RDWR | os.O_CREAT | os.O_NOFOLLOW, 0o644)
        except OSError as exc:
            if exc.errno == errno.ELOOP:
                raise StoreError(
                    f"{self.lock_path} is a symbolic link; the results folder "
                    f"must hold only the tool's own files: remove it"
                ) from None
            raise
        if not stat_is_regular(fd):
            os.close(fd)
            raise StoreError(f"{self.lock_path} is not a regular file: remove it")
        start = time.monotonic()
        try:
            while True:
                try:
                    fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
                    break
                except OSError as exc:
                    if exc.errno not in (errno.EAGAIN, errno.EACCES, errno.EWOULDBLOCK):
                        raise
                    holder = self.lock_holder() or "another run"
                    if not wait or (timeout is not None and time.monotonic() - start > timeout):
                        raise StoreLockedError(
                            f"results root {self.root} is in use by {holder}; two runs on one "
                            f"results root would corrupt it. Wait for it to finish or pass "
                            f"--wait"
                        ) from None
                    time.sleep(poll_s)
            info = json.dumps(
                {"owner": owner, "pid": os.getpid(), "host": socket.gethostname(), "since": iso(utc_now())}
            )
            os.ftruncate(fd, 0)
            os.pwrite(fd, info.encode(), 0)
            self.remove_stale_temp_files()
            try:
                yield
            finally:
                os.ftruncate(fd, 0)
                fcntl.flock(fd, fcntl.LOCK_UN)
        finally:
            os.close(fd)

    def ensure_unlocked(self) -> None:
        """Refuse early (before any orchestration starts) when another run holds the root.
        Advisory: the run still takes :meth:`lock`, which is what guarantees exclusion."""
        if not self.lock_path.exists():
            return
        with self.lock("probe"):
            pass

    def remove_stale_temp_files(self) -> list[Path]:
        """Delete the temp files (``.<name>.<random>.tmp``) of writers that died mid-write
        (SIGKILL, power loss: their ``except`` never ran). Only called while holding the
        lock, so no live writer owns them; the files they were replacing are intact."""
        removed = []
        for d in (
            self.root,
            self.runs_dir,
            self.root / "cache",
            self.root / "qa",
            *(self.calibrations_dir.glob("*") if self.calibrations_dir.is_dir() else ()),
            *(self.tables_dir.glob("*") if self.tables_dir.is_dir() else ()),
        ):
            if not d.is_dir():
                continue
            for p in d.glob(".*.tmp"):
                try:
                    p.unlink()
                    removed.append(p)
                except FileNotFoundError:
                    pass
        return removed

    def lock_holder(self) -> str | None:
        try:
            info = json.loads(self.lock_path.read_text() or "{}")
        except (OSError, ValueError):
            return None
        if not info:
            return None
        return (
            f"run {info.get('owner')} (pid {info.get('pid')} on {info.get('host')}, "
            f"since {info.get('since')})"
        )
