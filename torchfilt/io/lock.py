"""A directory that one process at a time writes: :class:`DirectoryLock`.

The lock is an OS lock (``fcntl.flock``) on a lock file in the directory, which also records the
holder's process id for the message of a refused second writer. The operating system releases it
when its holder exits, however it exits: a run killed with ``SIGKILL`` leaves a lock file that
nobody holds, and the next process takes it over (a killed run still resumes). Where ``fcntl`` is
unavailable (Windows) the lock is a no-op.
"""

from __future__ import annotations

import os
from pathlib import Path
from types import TracebackType
from typing import IO

from torchfilt.exceptions import RunError

try:
    import fcntl
except ImportError:  # pragma: no cover - not POSIX
    fcntl = None  # type: ignore[assignment]

__all__ = ["LOCK_NAME", "DirectoryLock"]

#: the lock file's name in the locked directory
LOCK_NAME = ".torchfilt.lock"


class DirectoryLock:
    """An exclusive, non-blocking lock on a directory (see the module docstring).

    Use as a context manager, or :meth:`acquire` and :meth:`release` (both idempotent).

    Args:
        directory: the directory to lock (it must exist).
        what: what the directory holds, for the message (``"run"``).
    """

    def __init__(self, directory: str | Path, *, what: str = "run") -> None:
        self.directory = Path(directory)
        self.path = self.directory / LOCK_NAME
        self.what = what
        self._file: IO[str] | None = None

    def acquire(self) -> DirectoryLock:
        """Take the lock.

        Returns:
            ``self``.

        Raises:
            RunError: another live process holds it (the message names the directory and the
                holder's pid).
        """
        if self._file is not None or fcntl is None:
            return self
        while True:
            f = open(self.path, "a+", encoding="utf-8")  # held until release
            try:
                fcntl.flock(f.fileno(), fcntl.LOCK_EX | fcntl.LOCK_NB)
            except OSError:
                f.seek(0)
                holder = f.read().strip() or "unknown"
                f.close()
                raise RunError(
                    f"{self.directory}: another process (pid {holder}) is writing this "
                    f"{self.what}; wait for it to finish or stop it, or choose another --out"
                ) from None
            try:  # the holder before us may have removed the file it held: lock the current one
                same = os.path.samestat(os.fstat(f.fileno()), os.stat(self.path))
            except FileNotFoundError:
                same = False
            if same:
                break
            f.close()
        f.seek(0)
        f.truncate()
        f.write(f"{os.getpid()}\n")
        f.flush()
        self._file = f
        return self

    def release(self) -> None:
        """Give the lock up and remove the lock file (nothing if not held)."""
        f, self._file = self._file, None
        if f is None:
            return
        try:
            self.path.unlink(missing_ok=True)  # while still held: no one else locks it meanwhile
        finally:
            f.close()  # closing releases the flock

    def __enter__(self) -> DirectoryLock:
        return self.acquire()

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.release()
