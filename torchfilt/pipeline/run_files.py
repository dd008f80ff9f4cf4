"""A run directory's files and log (see :mod:`torchfilt.pipeline.run`): the stage files and
checkpoints (atomic writes, clear errors for unusable ones), ``train.log`` and the stages' log
lines (why a fit ended, its estimated time)."""

from __future__ import annotations

import datetime as _dt
import io
import re
import shutil
from pathlib import Path
from typing import Any, TextIO

import torch
from torch import Tensor

from torchfilt.exceptions import RunError
from torchfilt.io import atomic_write_bytes
from torchfilt.io.atomic import output_error
from torchfilt.pipeline.run_checks import STAGES

__all__ = ["ESTIMATE_AFTER"]


def _now() -> str:
    return _dt.datetime.now(_dt.UTC).isoformat(timespec="seconds")


def _tensor_list(v: Tensor) -> Any:
    v = v.detach().cpu()
    return v.item() if v.numel() == 1 else v.tolist()


#: Iterations after which a stage logs its estimated remaining time.
ESTIMATE_AFTER = 5


class _StageClock:
    """Logs, once, a stage's estimated remaining time: after :data:`ESTIMATE_AFTER` iterations
    of this process (a resumed stage counts from where it resumed), at their mean rate."""

    def __init__(self, stage: str, total: int, log: _Log) -> None:
        self.stage, self.total, self.log = stage, int(total), log
        self.first: tuple[int, float] | None = None
        self.done = False

    def tick(self, iteration: int, elapsed: float) -> None:
        """Record iteration ``iteration`` ending ``elapsed`` seconds into the fit."""
        if self.done:
            return
        if self.first is None:
            self.first = (iteration, elapsed)
            return
        it0, t0 = self.first
        if iteration - it0 < ESTIMATE_AFTER or iteration >= self.total:
            return
        self.done = True
        rate = (elapsed - t0) / (iteration - it0)
        left = rate * (self.total - iteration)
        self.log(
            f"{self.stage}: about {left:.0f} s left at most ({rate:.2g} s per iteration, "
            f"{self.total - iteration} iterations to the budget; it stops earlier when it "
            "converges)"
        )


class _Log:
    """Plain lines to ``train.log`` (always) and to the console when progress is off."""

    def __init__(self, path: Path, echo: TextIO | None) -> None:
        self.path = path
        try:
            self.fh = open(path, "a", encoding="utf-8")
        except OSError as e:
            raise output_error(path, e) from None
        self.echo = echo

    def __call__(self, msg: str) -> None:
        line = f"{_now()} {msg}\n"
        try:
            self.fh.write(line)
            self.fh.flush()
        except OSError as e:
            raise output_error(self.path, e) from None
        if self.echo is not None:
            self.echo.write(msg + "\n")
            self.echo.flush()

    def close(self) -> None:
        self.fh.close()


def _remove(path: Path) -> None:
    """Remove a run file, or a stage checkpoint folder (of a data-parallel fit), if present."""
    if path.is_dir() and not path.is_symlink():
        shutil.rmtree(path)
    elif path.is_file():
        path.unlink()


def _load_checkpoint(path: Path) -> dict[str, Any]:
    """Read a checkpoint written by this module (plain data only), with a clear error if unusable."""
    try:
        ckpt = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as e:
        raise RunError(
            f"{path}: unreadable checkpoint ({type(e).__name__}); delete it to restart the stage "
            "it belongs to"
        ) from None
    if not isinstance(ckpt, dict) or ckpt.get("stage") not in STAGES or "fit" not in ckpt:
        raise RunError(
            f"{path}: not a torchfilt training checkpoint; delete it to restart the stage"
        )
    return ckpt


def _load_stage(path: Path) -> dict[str, Any]:
    """A finished stage's entry (plain data only), with a clear error if unusable."""
    try:
        entry = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as e:
        raise RunError(
            f"{path}: unreadable stage file ({type(e).__name__}); delete it to retrain the stage"
        ) from None
    if not isinstance(entry, dict) or "kind" not in entry:
        raise RunError(f"{path}: not a torchfilt stage file; delete it to retrain the stage")
    return entry


def _save(path: Path, obj: dict[str, Any]) -> None:
    """``torch.save`` into memory, then one atomic write (temporary file + rename)."""
    buf = io.BytesIO()
    torch.save(obj, buf)
    atomic_write_bytes(path, buf.getvalue())


def _fmt(v: list[float]) -> str:
    return "[" + ", ".join(f"{x:.4g}" for x in v) + "]"


def _ended(stopped: str, iterations: int, section: str) -> str:
    """Why a stage's fit ended, for the log: a fit that used its whole budget says so and how to
    give it more (``stopped`` is the fit's own ``"iterations"``, ``"converged"``, ...)."""
    its = f"{iterations} iteration{'s' if iterations != 1 else ''}"
    if stopped == "iterations":
        return (
            f"stopped at its budget of {its}, not converged (a new run with a larger "
            f"[{section}] iterations fits longer; --resume keeps the recipe as it is)"
        )
    if stopped == "no improvement" and section == "measurement_only":
        return (
            f"no improvement after {its}: no EM step raised the filter likelihood (its E-step is "
            'an approximation), which need not be the maximum; method = "likelihood" may go '
            'further: method = "auto" runs both and keeps the better on the validation '
            "recordings"
        )
    return f"{stopped} after {its}"


def _checkpoint_iteration(path: Path, method: str = "") -> int:
    """The iteration a stage checkpoint resumes from: that of its file, or the lowest of the files
    in its folder (a data-parallel fit's processes agree on the latest iteration all of them
    saved: ``rank{r}.ckpt``, or ``rank{r}.{method}.ckpt`` for one method of ``method = "auto"``
    or ``"both"``); 0 where unreadable."""
    if path.is_dir():
        name = re.compile(rf"rank\d+{re.escape('.' + method) if method else ''}\.ckpt")
        files = [p for p in sorted(path.glob("*.ckpt")) if name.fullmatch(p.name)]
        return min((_checkpoint_iteration(p) for p in files), default=0)
    try:
        ck = torch.load(path, map_location="cpu", weights_only=True)
        return int(ck["iteration"])
    except Exception:
        return 0
