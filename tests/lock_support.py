"""A second process holding a directory lock, for the lock tests (tests/io, tests/pipeline)."""

from __future__ import annotations

import subprocess
import sys

HOLD = """
import sys
from torchfilt.io.lock import DirectoryLock
lock = DirectoryLock(sys.argv[1]).acquire()
print("locked", flush=True)
sys.stdin.read()  # hold until the parent closes stdin or kills us
lock.release()
"""


def hold_in_subprocess(directory) -> subprocess.Popen:
    """A second process holding the lock on ``directory``; returns once it holds it (it says so
    on stdout: a signal, not a delay)."""
    proc = subprocess.Popen(
        [sys.executable, "-c", HOLD, str(directory)],
        stdin=subprocess.PIPE,
        stdout=subprocess.PIPE,
        text=True,
    )
    assert proc.stdout is not None
    assert proc.stdout.readline().strip() == "locked"
    return proc
