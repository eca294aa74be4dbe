"""A closed output pipe (``mimucal ... | head``) ends a command quietly, as it ends ``seq``."""

from __future__ import annotations

import os
import signal
import sys

CLOSED_PIPE_EXIT = 128 + signal.SIGPIPE  # 141: what a shell reports for a Unix tool the pipe ended


def closed_pipe_exit() -> int:
    """Point stdout and stderr at /dev/null (so that the interpreter's final flush of what is
    still buffered does not raise again and print "Exception ignored ... BrokenPipeError")
    and return the exit code of a command its reader stopped."""
    devnull = os.open(os.devnull, os.O_WRONLY)
    for stream in (sys.stdout, sys.stderr):
        try:
            os.dup2(devnull, stream.fileno())
        except (OSError, ValueError, AttributeError):  # not a real file (tests' capture)
            pass
    os.close(devnull)
    return CLOSED_PIPE_EXIT
