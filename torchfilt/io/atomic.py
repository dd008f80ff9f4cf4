"""Safe output files: atomic writes, output folders, the no-overwrite rule, and file hashing.

Every file torchfilt writes goes through :func:`atomic_write`: the content fills a temporary file
in the destination's folder, is flushed to disk, and then replaces the destination by a rename. A
reader (or a resumed run) sees either the old file or the complete new one, never a partial file,
even if the process is killed mid-write. The temporary file is named
``.{name}.{pid}.{random}.tmp``; one left behind by a killed process (its pid no longer runs) is
removed by the next write into that folder (:func:`clean_stale_temps`). Files are created with the
mode ``0o666`` less the process umask, like ``open(path, "w")``.

An ``OSError`` while writing (a full disk, a read-only folder, an output folder that is a file) is
raised as :class:`~torchfilt.exceptions.OutputError` naming the path.
"""

from __future__ import annotations

import errno
import hashlib
import os
import re
import tempfile
from collections.abc import Callable, Iterable
from pathlib import Path
from typing import BinaryIO

from torchfilt.exceptions import OutputError

__all__ = [
    "atomic_write",
    "atomic_write_bytes",
    "atomic_write_text",
    "check_new_outputs",
    "clean_stale_temps",
    "output_dir",
    "output_error",
    "sha256_file",
]

#: Temporary files of :func:`atomic_write`: ``.{name}.{pid}.{random}.tmp``.
_TEMP = re.compile(r"^\..+\.(\d+)\.[A-Za-z0-9_]+\.tmp$")


def _umask() -> int:
    """The process umask: read from ``/proc`` where it can be (no change of process state),
    else set and restored."""
    try:
        with open("/proc/self/status", encoding="ascii") as fh:
            for line in fh:
                if line.startswith("Umask:"):
                    return int(line.split()[1], 8)
    except (OSError, ValueError, IndexError):
        pass
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


def _describe(e: OSError) -> str:
    if e.errno in (errno.ENOSPC, errno.EDQUOT):
        return "no space left on the device (free some space, or write elsewhere)"
    if e.errno in (errno.EACCES, errno.EPERM, errno.EROFS):
        return "permission denied (the folder is read-only; choose another output)"
    if e.errno == errno.ENOTDIR:
        return "a parent of this path is a file, not a folder"
    if e.errno == errno.EISDIR:
        return "is a folder, not a file"
    return e.strerror or type(e).__name__


def output_error(path: str | Path, e: OSError) -> OutputError:
    """The :class:`OutputError` for an ``OSError`` raised while writing ``path``."""
    err = OutputError(f"{path}: cannot write: {_describe(e)}")
    err.errno = e.errno
    return err


def _alive(pid: int) -> bool:
    if pid == os.getpid():
        return True
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # exists, owned by someone else
        return True
    except OSError:
        return True
    return True


def clean_stale_temps(folder: str | Path) -> list[Path]:
    """Remove the temporary files that killed writes left in ``folder`` (not those of live
    processes). Returns the files removed; a folder that does not exist holds none."""
    folder = Path(folder)
    removed: list[Path] = []
    try:
        names = os.listdir(folder)
    except OSError:
        return removed
    for name in names:
        m = _TEMP.match(name)
        if m is None or _alive(int(m.group(1))):
            continue
        try:
            (folder / name).unlink()
            removed.append(folder / name)
        except OSError:
            pass
    return removed


def output_dir(path: str | Path) -> Path:
    """Create the output folder ``path`` (and its parents) if needed, and check it is usable.

    Raises:
        OutputError: ``path`` is a file, a parent is a file, or the folder cannot be created or
            written to (read-only).
    """
    path = Path(path)
    if path.exists() and not path.is_dir():
        raise OutputError(f"{path}: the output folder is a file; choose a folder")
    try:
        path.mkdir(parents=True, exist_ok=True)
    except FileExistsError:
        raise OutputError(f"{path}: a parent of the output folder is a file") from None
    except OSError as e:
        raise output_error(path, e) from None
    if not os.access(path, os.W_OK | os.X_OK):
        raise OutputError(f"{path}: the output folder is read-only; choose another output")
    clean_stale_temps(path)
    return path


def check_new_outputs(paths: Iterable[str | Path], *, force: bool) -> None:
    """Refuse to overwrite: raise if one of ``paths`` exists, unless ``force``.

    Raises:
        OutputError: naming the first existing path (and how to overwrite it).
    """
    if force:
        return
    for p in paths:
        if os.path.lexists(p):
            raise OutputError(
                f"{p}: exists and would be overwritten; pass --force (force=True) to replace it, "
                "or choose another output"
            )


def atomic_write(
    path: str | Path, write: Callable[[BinaryIO], None], *, fsync: bool = True
) -> Path:
    """Write ``path`` atomically: ``write`` fills a temporary file that then replaces ``path``.

    Args:
        path: destination.
        write: callback writing the content to a binary file object.
        fsync: flush the content to disk before the rename. The rename is atomic either way (a
            killed process leaves the old file or the new one); without the flush, an operating
            system crash or power loss can leave the new name with empty or partial content. Turn
            it off only for files whose loss or corruption is detected and harmless (a completion
            marker that is re-derived when unreadable).

    Returns:
        The destination path.

    Raises:
        OutputError: the file cannot be written (full disk, read-only folder, ...).
    """
    path = Path(path)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise output_error(path.parent, e) from None
    clean_stale_temps(path.parent)
    try:
        fd, tmp = tempfile.mkstemp(
            dir=path.parent, prefix=f".{path.name}.{os.getpid()}.", suffix=".tmp"
        )
    except OSError as e:
        raise output_error(path, e) from None
    try:
        os.fchmod(fd, 0o666 & ~_umask())
        with os.fdopen(fd, "wb") as fh:
            write(fh)
            fh.flush()
            if fsync:
                os.fsync(fh.fileno())
        os.replace(tmp, path)
    except OSError as e:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise output_error(path, e) from None
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise
    return path


def atomic_write_bytes(path: str | Path, data: bytes, *, fsync: bool = True) -> Path:
    """Write bytes atomically (``fsync``: see :func:`atomic_write`)."""

    def write(fh: BinaryIO) -> None:
        fh.write(data)

    return atomic_write(path, write, fsync=fsync)


def atomic_write_text(path: str | Path, text: str, *, fsync: bool = True) -> Path:
    """Write UTF-8 text atomically (``fsync``: see :func:`atomic_write`)."""
    return atomic_write_bytes(path, text.encode("utf-8"), fsync=fsync)


def sha256_file(path: str | Path, chunk: int = 1 << 20) -> str:
    """Hex SHA-256 of a file's content."""
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        while block := fh.read(chunk):
            h.update(block)
    return h.hexdigest()
