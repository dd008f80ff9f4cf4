"""The dataset manifest: channels with roles and units, the sample time, and the recordings."""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from torchfilt.io.atomic import atomic_write_text
from torchfilt.io.errors import DataError

__all__ = ["ROLES", "SCHEMA", "SPLITS", "Channel", "Manifest", "RecordingEntry"]

#: Channel roles.
ROLES = ("state", "input", "measurement")
#: Recording splits.
SPLITS = ("train", "validation", "test")
#: Manifest schema identifier.
SCHEMA = "torchfilt.dataset/1"


@dataclass(frozen=True)
class Channel:
    """One named column of a recording.

    Attributes:
        name: column name in the files.
        role: ``"state"``, ``"input"`` or ``"measurement"``.
        unit: physical unit (free text, may be empty).
    """

    name: str
    role: str
    unit: str = ""


@dataclass(frozen=True)
class RecordingEntry:
    """A recording listed in a manifest: a file (relative to the manifest) and its split."""

    file: str
    split: str = "train"


@dataclass(frozen=True)
class Manifest:
    """Describes a dataset: what the columns mean and which recording belongs to which split.

    Attributes:
        name: dataset name.
        sample_time: time between rows, in ``time_unit``.
        channels: the channels, in order.
        recordings: the recordings and their splits.
        time_column: name of the time column.
        time_unit: unit of time.
        description: free text.
    """

    name: str
    sample_time: float
    channels: tuple[Channel, ...]
    recordings: tuple[RecordingEntry, ...] = ()
    time_column: str = "time"
    time_unit: str = "s"
    description: str = ""
    extra: dict[str, Any] = field(default_factory=dict)

    def names(self, role: str) -> list[str]:
        """Names of the channels with ``role``, in order."""
        if role not in ROLES:
            raise ValueError(f"role must be one of {ROLES}, got {role!r}")
        return [c.name for c in self.channels if c.role == role]

    def units(self, role: str) -> list[str]:
        """Units of the channels with ``role``, in order."""
        return [c.unit for c in self.channels if c.role == role]

    @property
    def columns(self) -> list[str]:
        """All column names a recording must have: time first, then the channels."""
        return [self.time_column, *(c.name for c in self.channels)]

    # ------------------------------------------------------------------ (de)serialisation
    @classmethod
    def from_dict(cls, d: Any, *, path: str | Path | None = None) -> Manifest:
        """Build and validate a manifest from parsed JSON."""

        def fail(msg: str) -> DataError:
            return DataError(msg, path=path)

        if not isinstance(d, dict):
            raise fail("a manifest must be a JSON object")
        schema = d.get("schema", SCHEMA)
        if schema != SCHEMA:
            raise fail(f"unknown manifest schema {schema!r} (this version reads {SCHEMA!r})")
        for key in ("name", "sample_time", "channels"):
            if key not in d:
                raise fail(f"missing key {key!r}")
        try:
            dt = float(d["sample_time"])
        except (TypeError, ValueError):
            raise fail(f"sample_time must be a number, got {d['sample_time']!r}") from None
        if not (math.isfinite(dt) and dt > 0):
            raise fail(f"sample_time must be a finite positive number, got {dt}")
        time = d.get("time", {})
        time_column = str(time.get("name", "time")) if isinstance(time, dict) else "time"
        time_unit = str(time.get("unit", "s")) if isinstance(time, dict) else "s"
        if not isinstance(d["channels"], list) or not d["channels"]:
            raise fail("channels must be a non-empty list")
        channels = []
        for i, c in enumerate(d["channels"]):
            if not isinstance(c, dict) or "name" not in c or "role" not in c:
                raise fail(f"channels[{i}] must be an object with 'name' and 'role'")
            if c["role"] not in ROLES:
                raise fail(
                    f"channels[{i}] ({c['name']!r}): role must be one of {ROLES}, got {c['role']!r}"
                )
            channels.append(Channel(str(c["name"]), str(c["role"]), str(c.get("unit", ""))))
        names = [time_column] + [c.name for c in channels]
        dup = {n for n in names if names.count(n) > 1}
        if dup:
            raise fail(f"duplicate column names {sorted(dup)}")
        recs = []
        for i, r in enumerate(d.get("recordings", [])):
            if isinstance(r, str):
                r = {"file": r}
            if not isinstance(r, dict) or "file" not in r:
                raise fail(f"recordings[{i}] must be a file name or an object with 'file'")
            split = str(r.get("split", "train"))
            if split not in SPLITS:
                raise fail(
                    f"recordings[{i}] ({r['file']!r}): split must be one of {SPLITS}, got {split!r}"
                )
            recs.append(RecordingEntry(str(r["file"]), split))
        files = [r.file for r in recs]
        if len(set(files)) != len(files):
            raise fail("a recording is listed twice")
        known = {"schema", "name", "sample_time", "time", "channels", "recordings", "description"}
        return cls(
            name=str(d["name"]),
            sample_time=dt,
            channels=tuple(channels),
            recordings=tuple(recs),
            time_column=time_column,
            time_unit=time_unit,
            description=str(d.get("description", "")),
            extra={k: v for k, v in d.items() if k not in known},
        )

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready dictionary."""
        return {
            "schema": SCHEMA,
            "name": self.name,
            "description": self.description,
            "sample_time": self.sample_time,
            "time": {"name": self.time_column, "unit": self.time_unit},
            "channels": [{"name": c.name, "role": c.role, "unit": c.unit} for c in self.channels],
            "recordings": [{"file": r.file, "split": r.split} for r in self.recordings],
            **self.extra,
        }

    @classmethod
    def load(cls, path: str | Path) -> Manifest:
        """Read a manifest JSON file."""
        path = Path(path)
        if not path.is_file():
            raise DataError("manifest not found", path=path)
        try:
            d = json.loads(path.read_text(encoding="utf-8"))
        except (UnicodeDecodeError, json.JSONDecodeError) as e:
            raise DataError(f"not a JSON manifest ({e})", path=path) from None
        return cls.from_dict(d, path=path)

    def save(self, path: str | Path) -> Path:
        """Write the manifest atomically."""
        return atomic_write_text(path, json.dumps(self.to_dict(), indent=2) + "\n")
