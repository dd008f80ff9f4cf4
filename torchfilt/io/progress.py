"""Progress display: a bar on a terminal, plain lines in logs."""

from __future__ import annotations

import sys
import time
from typing import TextIO

__all__ = ["ProgressBar"]


class ProgressBar:
    """A one-line progress bar that redraws in place on a terminal.

    When the stream is not a terminal (a log file, CI), it writes a plain line every tenth of the
    work instead, so logs stay readable.

    Args:
        label: what is being done.
        total: number of units of work.
        stream: output stream (default ``sys.stderr``).
        enabled: draw anything at all.
    """

    WIDTH = 28

    def __init__(
        self, label: str, total: int, stream: TextIO | None = None, enabled: bool = True
    ) -> None:
        self.label, self.total = label, max(1, total)
        self.stream = stream if stream is not None else sys.stderr
        self.enabled = enabled
        self.tty = bool(getattr(self.stream, "isatty", lambda: False)())
        self.start = time.perf_counter()
        self._last_line = -1

    def update(self, done: int, info: str = "") -> None:
        """Show ``done`` of ``total`` units, with extra ``info`` text."""
        if not self.enabled:
            return
        elapsed = time.perf_counter() - self.start
        frac = min(1.0, done / self.total)
        if self.tty:
            fill = round(frac * self.WIDTH)
            bar = "#" * fill + "-" * (self.WIDTH - fill)
            eta = elapsed / frac * (1 - frac) if frac > 0 else float("nan")
            self.stream.write(
                f"\r{self.label} [{bar}] {done}/{self.total} {info} {elapsed:5.1f}s (eta {eta:4.0f}s)  "
            )
            if done >= self.total:
                self.stream.write("\n")
        else:
            tenth = int(frac * 10)
            if tenth == self._last_line and done < self.total:
                return
            self._last_line = tenth
            self.stream.write(f"{self.label}: {done}/{self.total} {info} ({elapsed:.1f} s)\n")
        self.stream.flush()
