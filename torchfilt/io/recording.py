"""One recording: a time column and named channels, read from and written to CSV or NPZ."""

from __future__ import annotations

import csv
import difflib
import io
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from torch import Tensor

from torchfilt.exceptions import InputError, MissingKeyError
from torchfilt.io.atomic import atomic_write, atomic_write_text
from torchfilt.io.errors import DataError
from torchfilt.io.manifest import ROLES, Channel, Manifest

__all__ = ["SUFFIXES", "Recording", "read_recording", "write_recording"]

#: Supported file types.
SUFFIXES = (".csv", ".npz")
#: Cells (case-insensitive, besides an empty cell) that mean "not observed".
MISSING_CELLS = ("nan", "na")
#: Relative tolerance on the time step against the manifest's sample time.
SAMPLE_TIME_RTOL = 1e-6
_ZIP_MAGIC = b"PK\x03\x04"


@dataclass
class Recording:
    """A validated recording.

    Attributes:
        time: sample times, shape ``(T,)``, strictly increasing.
        data: channel values in the order of ``channels``, shape ``(T, C)``; NaN = not observed.
        channels: the channels.
        path: the file it came from, if any.
        time_column: name of the time column.
    """

    time: np.ndarray
    data: np.ndarray
    channels: tuple[Channel, ...]
    path: Path | None = None
    time_column: str = "time"

    def __len__(self) -> int:
        return int(self.time.shape[0])

    @property
    def name(self) -> str:
        """The file stem, or ``"recording"``."""
        return self.path.stem if self.path is not None else "recording"

    def column(self, name: str) -> np.ndarray:
        """One channel.

        Args:
            name: the channel's name.

        Returns:
            Its values, shape ``(T,)``.

        Raises:
            MissingKeyError: the recording has no channel ``name``.
        """
        for i, c in enumerate(self.channels):
            if c.name == name:
                return self.data[:, i]
        raise MissingKeyError(
            f"{self.name}: no channel {name!r}; channels are {[c.name for c in self.channels]}"
        )

    def names(self, role: str) -> list[str]:
        """Channel names with ``role``.

        Args:
            role: ``"state"``, ``"input"`` or ``"measurement"``.

        Returns:
            The names, in column order.

        Raises:
            InputError: ``role`` is not a channel role.
        """
        if role not in ROLES:
            raise InputError(f"role must be one of {ROLES}, got {role!r}")
        return [c.name for c in self.channels if c.role == role]

    def role(self, role: str) -> np.ndarray:
        """Columns with ``role``.

        Args:
            role: ``"state"``, ``"input"`` or ``"measurement"``.

        Returns:
            The columns, shape ``(T, k)`` (``k`` may be 0).

        Raises:
            InputError: ``role`` is not a channel role.
        """
        idx = [i for i, c in enumerate(self.channels) if c.role == role]
        if role not in ROLES:
            raise InputError(f"role must be one of {ROLES}, got {role!r}")
        return self.data[:, idx]

    def tensor(self, role: str, dtype: torch.dtype = torch.float64) -> Tensor:
        """Columns with ``role`` as a tensor.

        Args:
            role: ``"state"``, ``"input"`` or ``"measurement"``.
            dtype: the tensor's dtype.

        Returns:
            The columns, shape ``(T, k)`` (``k`` may be 0).

        Raises:
            InputError: ``role`` is not a channel role.
        """
        return torch.as_tensor(self.role(role), dtype=dtype)

    @property
    def states(self) -> Tensor:
        """State channels ``(T, n)``."""
        return self.tensor("state")

    @property
    def inputs(self) -> Tensor | None:
        """Input channels ``(T, nu)``, or ``None`` when there are none."""
        u = self.tensor("input")
        return None if u.shape[-1] == 0 else u

    @property
    def measurements(self) -> Tensor:
        """Measurement channels ``(T, m)``, NaN where not observed."""
        return self.tensor("measurement")

    @classmethod
    def from_arrays(
        cls,
        time: np.ndarray | Tensor,
        channels: Sequence[Channel],
        columns: Mapping[str, np.ndarray | Tensor],
        *,
        time_column: str = "time",
    ) -> Recording:
        """Build a recording from arrays.

        Args:
            time: the time of each row, shape ``(T,)``, finite and strictly increasing.
            channels: the channels, in column order.
            columns: one array or tensor per channel name, each of shape ``(T,)``.
            time_column: name of the time column.

        Returns:
            The recording (with no file).

        Raises:
            DataError: a channel without data, a column whose shape is not the time's, or a time
                that is not finite and strictly increasing.
        """
        t = np.asarray(torch.as_tensor(time).detach().cpu(), dtype=np.float64)
        cols = []
        for c in channels:
            if c.name not in columns:
                raise DataError(f"no data for channel {c.name!r}", column=c.name)
            a = np.asarray(torch.as_tensor(columns[c.name]).detach().cpu(), dtype=np.float64)
            if a.shape != t.shape:
                raise DataError(f"has shape {a.shape}, time has {t.shape}", column=c.name)
            cols.append(a)
        data = np.stack(cols, axis=-1) if cols else np.zeros((t.shape[0], 0))
        rec = cls(t, data, tuple(channels), None, time_column)
        _check_time(rec.time, None, None, time_column)
        return rec


# ---------------------------------------------------------------------------- reading
def _suggest(name: str, have: Sequence[str]) -> str:
    close = difflib.get_close_matches(name, have, n=1)
    return f"; did you mean {close[0]!r}?" if close else ""


def _check_time(
    t: np.ndarray,
    path: Path | None,
    sample_time: float | None,
    time_column: str,
    csv_lines: np.ndarray | None = None,
) -> None:
    def where(i: int) -> dict[str, int]:
        return {"line": int(csv_lines[i])} if csv_lines is not None else {"row": i}

    bad = ~np.isfinite(t)
    if bad.any():
        i = int(np.argmax(bad))
        raise DataError("time must be finite", path=path, column=time_column, **where(i))
    if t.shape[0] >= 2:
        d = np.diff(t)
        nonmono = d <= 0
        if nonmono.any():
            i = int(np.argmax(nonmono)) + 1
            raise DataError(
                f"time is not strictly increasing: {t[i]:g} follows {t[i - 1]:g}",
                path=path,
                column=time_column,
                **where(i),
            )
        if sample_time is not None:
            off = np.abs(d - sample_time) > SAMPLE_TIME_RTOL * sample_time
            if off.any():
                i = int(np.argmax(off)) + 1
                raise DataError(
                    f"time step {d[i - 1]:g} differs from the manifest's sample_time {sample_time:g} "
                    "(resample onto a regular grid; mark missing measurements with NaN)",
                    path=path,
                    column=time_column,
                    **where(i),
                )


def _read_csv(
    path: Path, want: list[str], maybe: set[str]
) -> tuple[dict[str, np.ndarray], np.ndarray | None]:
    """The columns, and the file line of each data row (blank lines counted, header = its line)."""
    raw = path.read_bytes()
    if raw.startswith(_ZIP_MAGIC):
        raise DataError("is a zip/NPZ archive, not a CSV file (check the extension)", path=path)
    if b"\x00" in raw[:4096]:
        raise DataError("contains binary data, not CSV text (check the extension)", path=path)
    try:
        text = raw.decode("utf-8-sig")
    except UnicodeDecodeError as e:
        raise DataError(
            f"is not UTF-8 CSV text ({e.reason} at byte {e.start})", path=path
        ) from None
    reader = csv.reader(io.StringIO(text, newline=""))
    rows: list[tuple[int, list[str]]] = []  # (line in the file, fields); blank lines skipped
    try:
        for row in reader:
            if row and not (len(row) == 1 and not row[0].strip()):
                rows.append((reader.line_num, row))
    except csv.Error as e:
        raise DataError(f"unreadable CSV ({e})", path=path, line=reader.line_num) from None
    if not rows:
        raise DataError("is empty (no header row)", path=path)
    header_line, header = rows[0][0], [h.strip() for h in rows[0][1]]
    dup = {h for h in header if header.count(h) > 1}
    if dup:
        raise DataError(f"duplicate column names {sorted(dup)}", path=path, line=header_line)
    for name in want:
        if name not in header and name not in maybe:
            raise DataError(
                f"missing column; the file has columns {header}{_suggest(name, header)}",
                path=path,
                column=name,
                line=header_line,
            )
    want = [n for n in want if n in header]
    idx = {h: i for i, h in enumerate(header)}
    out = {name: np.empty(len(rows) - 1) for name in want}
    lines = np.array([ln for ln, _ in rows[1:]], dtype=np.int64)
    for r, (line, row) in enumerate(rows[1:]):
        if len(row) != len(header):
            raise DataError(
                f"has {len(row)} fields, the header has {len(header)}", path=path, line=line
            )
        for name in want:
            s = row[idx[name]].strip()
            if s == "" or s.lower() in MISSING_CELLS:
                out[name][r] = math.nan
                continue
            try:
                v = float(s)
            except ValueError:
                raise DataError(
                    f"cannot read {s!r} as a number", path=path, column=name, line=line
                ) from None
            if math.isinf(v):
                raise DataError(
                    f"{s!r} is not a finite number (leave the cell empty, or write nan, for a "
                    "missing value)",
                    path=path,
                    column=name,
                    line=line,
                )
            out[name][r] = v
    return out, lines


def _read_npz(
    path: Path, want: list[str], maybe: set[str]
) -> tuple[dict[str, np.ndarray], np.ndarray | None]:
    """The arrays (rows are named by index: no line numbers)."""
    with open(path, "rb") as fh:
        head = fh.read(4)
    if head != _ZIP_MAGIC:
        raise DataError("is not an NPZ (zip) archive (check the extension)", path=path)
    try:
        with open(path, "rb") as fh, np.load(fh, allow_pickle=False) as z:
            have = list(z.files)
            out = {}
            for name in want:
                if name not in have and name in maybe:
                    continue
                if name not in have:
                    raise DataError(
                        f"missing array; the archive has {have}{_suggest(name, have)}",
                        path=path,
                        column=name,
                    )
                a = z[name]
                if a.ndim != 1 or not np.issubdtype(a.dtype, np.number):
                    raise DataError(
                        f"must be a 1-D numeric array, got {a.dtype} {a.shape}",
                        path=path,
                        column=name,
                    )
                if np.iscomplexobj(a):
                    raise DataError(
                        f"is complex ({a.dtype}); channels must be real numbers",
                        path=path,
                        column=name,
                    )
                out[name] = a.astype(np.float64)
                bad = np.isinf(out[name])
                if bad.any():
                    raise DataError(
                        "is not a finite number (use NaN for a missing value)",
                        path=path,
                        column=name,
                        row=int(np.argmax(bad)),
                    )
    except DataError:
        raise
    except ValueError as e:  # object arrays need pickle: refused
        raise DataError(f"cannot be read safely ({e})", path=path) from None
    except Exception as e:  # corrupt archive
        raise DataError(
            f"is not a readable NPZ archive ({type(e).__name__}: {e})", path=path
        ) from None
    lengths = {n: a.shape[0] for n, a in out.items()}
    if len(set(lengths.values())) > 1:
        raise DataError(f"arrays have different lengths {lengths}", path=path)
    return out, None


def read_recording(
    path: str | Path,
    spec: Manifest | Sequence[Channel],
    *,
    time_column: str | None = None,
    sample_time: float | None = None,
    require_finite: Sequence[str] = (),
    optional: Sequence[str] = (),
) -> Recording:
    """Read and validate one recording.

    Args:
        path: a ``.csv`` or ``.npz`` file.
        spec: the manifest (channels, time column, sample time) or a list of channels.
        time_column: name of the time column (default: the manifest's, else ``"time"``).
        sample_time: expected time step (default: the manifest's); ``None`` skips the check.
        require_finite: roles that may not contain NaN (``("state", "input")`` for training data).
        optional: roles whose columns may be absent (read as all-NaN), e.g. ``("state",)`` when
            filtering logs that may or may not carry ground truth.

    Returns:
        The recording.

    Raises:
        DataError: missing or misnamed columns, a file that is not what its extension says,
            unparsable values, non-monotonic time, a time step off the sample time, or NaN in a
            channel whose role is in ``require_finite``. The message names the file, the column
            and the line (CSV; the header is line 1) or row (NPZ).
    """
    path = Path(path)
    if isinstance(spec, Manifest):
        channels = spec.channels
        time_column = time_column or spec.time_column
        sample_time = spec.sample_time if sample_time is None else sample_time
    else:
        channels = tuple(spec)
        time_column = time_column or "time"
    if not path.is_file():
        raise DataError("recording not found", path=path)
    suffix = path.suffix.lower()
    if suffix not in SUFFIXES:
        raise DataError(f"unsupported file type {suffix!r}; use one of {SUFFIXES}", path=path)
    want = [time_column, *(c.name for c in channels)]
    maybe = {c.name for c in channels if c.role in optional}
    cols, lines = (_read_csv if suffix == ".csv" else _read_npz)(path, want, maybe)
    t = cols[time_column]
    for name in maybe:
        if name not in cols:
            cols[name] = np.full(t.shape, np.nan)
    if t.shape[0] == 0:
        raise DataError("has no rows", path=path)
    _check_time(t, path, sample_time, time_column, csv_lines=lines)
    for c in channels:
        if c.role in require_finite:
            bad = ~np.isfinite(cols[c.name])
            if bad.any():
                i = int(np.argmax(bad))
                where = {"line": int(lines[i])} if lines is not None else {"row": i}
                raise DataError(
                    f"{c.role} channels of training data may not be missing (NaN)",
                    path=path,
                    column=c.name,
                    **where,
                )
    data = np.stack([cols[c.name] for c in channels], axis=-1)
    return Recording(t, data, tuple(channels), path, time_column)


# ---------------------------------------------------------------------------- writing
def write_recording(rec: Recording, path: str | Path, *, precision: int = 17) -> Path:
    """Write a recording atomically as CSV (``precision`` significant digits) or NPZ.

    Args:
        rec: the recording.
        path: destination; the suffix selects the format.
        precision: significant digits in CSV (17 round-trips float64 exactly).

    Returns:
        The path written.

    Raises:
        DataError: an infinite value (refused on reading too), or an unknown suffix.
    """
    path = Path(path)
    suffix = path.suffix.lower()
    names = [rec.time_column, *(c.name for c in rec.channels)]
    # the reading rule refuses infinite values (NaN is "not observed"): never write one
    inf = np.isinf(rec.data)
    if bool(inf.any()):
        row, col = (int(v[0]) for v in np.nonzero(inf))
        raise DataError(
            "infinite value; a recording holds finite values or NaN (not observed)",
            path=path,
            column=rec.channels[col].name,
            row=row,
        )
    if suffix == ".csv":
        buf = io.StringIO()
        w = csv.writer(buf, lineterminator="\n")
        w.writerow(names)
        fmt = f"{{:.{precision}g}}"
        for i in range(len(rec)):
            vals = [rec.time[i], *rec.data[i]]
            w.writerow(["nan" if not math.isfinite(v) else fmt.format(v) for v in vals])
        return atomic_write_text(path, buf.getvalue())
    if suffix == ".npz":
        arrays = {
            rec.time_column: rec.time,
            **{c.name: rec.data[:, i] for i, c in enumerate(rec.channels)},
        }
        return atomic_write(path, lambda fh: np.savez(fh, **arrays))  # type: ignore[arg-type]
    raise DataError(f"unsupported file type {suffix!r}; use one of {SUFFIXES}", path=path)
