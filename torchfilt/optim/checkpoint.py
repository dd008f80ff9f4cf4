"""Checkpoint files of the fitting loop: atomic writes, a fingerprint of the fit, and the
agreement of a data-parallel fit's processes on where to resume.

The atomic write itself is passed in (``write``: :func:`torchfilt.io.atomic_write` from the
training layer), so that this low layer needs no file-system policy of its own.
"""

from __future__ import annotations

import copy
import hashlib
from collections.abc import Callable
from pathlib import Path
from typing import Any, BinaryIO

import torch
from torch import Tensor

from torchfilt.exceptions import RunError

__all__ = ["AtomicWrite", "CheckpointFile", "fingerprint"]

#: ``write(path, fill)``: write ``path`` atomically, ``fill`` writing the content to a file.
AtomicWrite = Callable[[Path, Callable[[BinaryIO], None]], Any]


def fingerprint(*tensors: Tensor | None) -> str:
    """SHA-256 of the shapes and bytes of ``tensors`` (``None`` skipped): what a checkpoint of a
    fit must match (its data and initial values).

    Args:
        *tensors: the tensors, each of any shape, or ``None``.

    Returns:
        The hexadecimal digest.
    """
    h = hashlib.sha256()
    for t in tensors:
        if t is not None:
            h.update(str(tuple(t.shape)).encode())
            h.update(t.detach().cpu().contiguous().numpy().tobytes())
    return h.hexdigest()


def _kept(ck: dict[str, Any] | None) -> dict[str, Any] | None:
    """A deep copy of a checkpoint without its ``previous``: what the next data-parallel save
    keeps as its previous (the live history and optimiser state change after a save)."""
    if ck is None:
        return None
    return copy.deepcopy({k: v for k, v in ck.items() if k != "previous"})


class CheckpointFile:
    """The checkpoint file of one fit (one per process of a data-parallel fit).

    Args:
        path: the file.
        fingerprint: of the fit (see :func:`fingerprint`); a checkpoint with another is refused.
        schema: format tag written into the file and required of one read back.
        kind: the fit's name in messages (``"likelihood"``, ``"EM"``).
        write: the atomic write (:data:`AtomicWrite`).
        all_reduce: of a data-parallel fit: every checkpoint then also keeps the one before it
            (see :meth:`resume`).
    """

    def __init__(
        self,
        path: str | Path,
        fingerprint: str,
        *,
        schema: str,
        kind: str,
        write: AtomicWrite,
        all_reduce: Callable[[Tensor], None] | None = None,
    ) -> None:
        self.path, self.fingerprint = Path(path), fingerprint
        self.schema, self.kind, self.write = schema, kind, write
        self.all_reduce = all_reduce
        self.saved: dict[str, Any] | None = None  # the last checkpoint (data-parallel)

    def load(self) -> dict[str, Any]:
        """This fit's checkpoint.

        Returns:
            The checkpoint's dict.

        Raises:
            RunError: the file is unreadable, not a checkpoint of this kind, or one of another
                fit (it names the file).
        """
        path = self.path
        try:
            ck = torch.load(path, map_location="cpu", weights_only=True)
        except Exception as e:
            raise RunError(
                f"{path}: unreadable checkpoint ({type(e).__name__}); delete it to start again"
            ) from None
        if not isinstance(ck, dict) or ck.get("schema") != self.schema:
            raise RunError(
                f"{path}: not a torchfilt {self.kind} checkpoint; delete it to start again"
            )
        if ck.get("fingerprint") != self.fingerprint:
            raise RunError(
                f"{path}: the checkpoint belongs to another fit (different data, model, "
                "parameters or initial values); delete it to start again"
            )
        return ck

    def save(self, payload: dict[str, Any]) -> None:
        """Write ``payload`` (with the schema and the fingerprint) atomically; a data-parallel
        fit's file also keeps the checkpoint before it."""
        body = {"fingerprint": self.fingerprint, **payload}
        data = {"schema": self.schema, **body}
        if self.saved is not None:
            data["previous"] = {k: v for k, v in self.saved.items() if k != "previous"}

        def fill(fh: BinaryIO) -> None:
            torch.save(data, fh)

        self.write(self.path, fill)
        if self.all_reduce is not None:
            self.saved = _kept(body)

    def resume(self) -> dict[str, Any] | None:
        """The checkpoint to resume from (``None``: start afresh); a :class:`RunError` for one
        that belongs to another fit.

        In a data-parallel fit (``all_reduce``) the processes must resume from the same
        iteration, but a process that died stopped saving while the others may have saved one
        checkpoint more (the collectives keep them within one checkpoint of each other). So every
        checkpoint of a data-parallel fit also holds the one before it, and the processes agree
        here, with two collectives, on the latest iteration all of them have: one ahead of
        another resumes from its previous checkpoint. A process whose checkpoint cannot be used
        makes all of them raise (none is left waiting in a collective)."""
        ck = self._agreed()
        if self.all_reduce is not None:
            self.saved = _kept(ck)
        return ck

    def _agreed(self) -> dict[str, Any] | None:
        ck: dict[str, Any] | None = None
        error: RunError | None = None
        if self.path.is_file():
            try:
                ck = self.load()
            except RunError as e:
                error = e
        all_reduce, path = self.all_reduce, self.path
        if all_reduce is None:
            if error is not None:
                raise error
            return ck
        it = 0 if ck is None else int(ck["iteration"])
        flat = torch.tensor([1.0, float(it), float(error is not None)], dtype=torch.float64)
        all_reduce(flat)
        world, total, errors = (float(v) for v in flat)
        if errors > 0:
            if error is not None:
                raise error
            peer = RunError(
                f"{path}: another process of this data-parallel fit cannot use its checkpoint "
                "(its own error says why); delete the checkpoints of all processes to start again"
            )
            peer.peer = True  # type: ignore[attr-defined]  # a launcher reports the other's first
            raise peer
        if it * world > total and ck is not None:  # ahead of another process
            ck = ck.get("previous")
        it = 0 if ck is None else int(ck["iteration"])
        flat = torch.tensor([float(it), float(it) ** 2], dtype=torch.float64)
        all_reduce(flat)
        if abs(float(flat[0]) ** 2 - world * float(flat[1])) > 0.5:  # not all equal
            raise RunError(
                f"{path}: the checkpoints of this data-parallel fit's processes are more than one "
                f"checkpoint apart (this one at iteration {it}, mean "
                f"{float(flat[0]) / world:.4g}); delete the checkpoints of all processes to start "
                "again"
            )
        return ck
