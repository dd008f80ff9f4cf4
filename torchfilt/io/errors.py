"""The error raised for invalid recordings, manifests and datasets."""

from __future__ import annotations

from pathlib import Path

__all__ = ["DataError"]


class DataError(ValueError):
    """A data file is invalid. The message names the file and, where it applies, the column and row.

    Attributes:
        path: the offending file.
        column: the offending column, if any.
        line: the 1-based line in the file (CSV, header = line 1) or 0-based row (NPZ), if any.
    """

    def __init__(
        self,
        message: str,
        *,
        path: str | Path | None = None,
        column: str | None = None,
        line: int | None = None,
        row: int | None = None,
    ) -> None:
        where = []
        if path is not None:
            where.append(str(path))
        if column is not None:
            where.append(f"column {column!r}")
        if line is not None:
            where.append(f"line {line}")
        if row is not None:
            where.append(f"row {row}")
        super().__init__(f"{', '.join(where)}: {message}" if where else message)
        self.path = None if path is None else Path(path)
        self.column = column
        self.line = line
        self.row = row
