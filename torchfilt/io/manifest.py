"""The dataset manifest: channels with roles and units, the sample time, and the recordings."""

from __future__ import annotations

import json
import math
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from torchfilt.exceptions import InputError
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
        """Names of the channels with ``role``, in order.

        Args:
            role: ``"state"``, ``"input"`` or ``"measurement"``.

        Returns:
            The channel names.

        Raises:
            InputError: ``role`` is not a channel role.
        """
        if role not in ROLES:
            raise InputError(f"role must be one of {ROLES}, got {role!r}")
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
        """Build and validate a manifest from parsed JSON.

        Every value must have its JSON type (a number is not read as a name, a list not as a file
        name): what is given is what the :class:`Manifest` holds. Unknown top-level keys are kept
        in :attr:`extra`; unknown keys inside ``time``, a channel or a recording are refused.

        Raises:
            DataError: naming the file (``path``) and the key that is missing or invalid.
        """

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
        st = d["sample_time"]
        if isinstance(st, bool) or not isinstance(st, int | float):
            raise fail(f"sample_time must be a number, got {st!r}")
        dt = float(st)
        if not (math.isfinite(dt) and dt > 0):
            raise fail(f"sample_time must be a finite positive number, got {dt}")
        time = d.get("time", {})
        if not isinstance(time, dict):
            raise fail(f"time must be an object with 'name' and 'unit', got {time!r}")
        _known_keys(time, ("name", "unit"), "time", fail)
        time_column = _text(time.get("name", "time"), "time.name", fail, empty=False)
        time_unit = _text(time.get("unit", "s"), "time.unit", fail)
        channels = _channels(d["channels"], fail)
        names = [time_column] + [c.name for c in channels]
        dup = {n for n in names if names.count(n) > 1}
        if dup:
            raise fail(f"duplicate column names {sorted(dup)}")
        recs = _recordings(d.get("recordings", []), fail)
        files = [r.file for r in recs]
        if len(set(files)) != len(files):
            raise fail("a recording is listed twice")
        known = {"schema", "name", "sample_time", "time", "channels", "recordings", "description"}
        return cls(
            name=_text(d["name"], "name", fail),
            sample_time=dt,
            channels=tuple(channels),
            recordings=tuple(recs),
            time_column=time_column,
            time_unit=time_unit,
            description=_text(d.get("description", ""), "description", fail),
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
        """Read a manifest JSON file.

        Args:
            path: the manifest file.

        Returns:
            The validated manifest.

        Raises:
            DataError: the file is missing, is not JSON, or is not a valid manifest (the message
                names the file and the key).
        """
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


def _text(value: Any, key: str, fail: Callable[[str], DataError], *, empty: bool = True) -> str:
    """``value`` if it is a string (non-empty unless ``empty``); a DataError naming ``key``."""
    if not isinstance(value, str):
        raise fail(f"{key} must be a string, got {value!r}")
    if not empty and not value:
        raise fail(f"{key} must be a non-empty string")
    return value


def _known_keys(
    obj: dict[str, Any], keys: tuple[str, ...], where: str, fail: Callable[[str], DataError]
) -> None:
    unknown = sorted(str(k) for k in obj if k not in keys)
    if unknown:
        raise fail(f"{where}: unknown key(s) {unknown} (known: {', '.join(keys)})")


def _channels(given: Any, fail: Callable[[str], DataError]) -> list[Channel]:
    if not isinstance(given, list) or not given:
        raise fail(f"channels must be a non-empty list, got {given!r}")
    channels = []
    for i, c in enumerate(given):
        if not isinstance(c, dict) or "name" not in c or "role" not in c:
            raise fail(f"channels[{i}] must be an object with 'name' and 'role'")
        _known_keys(c, ("name", "role", "unit"), f"channels[{i}]", fail)
        name = _text(c["name"], f"channels[{i}].name", fail, empty=False)
        if c["role"] not in ROLES or not isinstance(c["role"], str):
            raise fail(f"channels[{i}] ({name!r}): role must be one of {ROLES}, got {c['role']!r}")
        unit = _text(c.get("unit", ""), f"channels[{i}].unit", fail)
        channels.append(Channel(name, c["role"], unit))
    return channels


def _recordings(given: Any, fail: Callable[[str], DataError]) -> list[RecordingEntry]:
    if not isinstance(given, list):
        raise fail(f"recordings must be a list, got {given!r}")
    recs = []
    for i, r in enumerate(given):
        if isinstance(r, str):
            r = {"file": r}
        if not isinstance(r, dict) or "file" not in r:
            raise fail(f"recordings[{i}] must be a file name or an object with 'file'")
        _known_keys(r, ("file", "split"), f"recordings[{i}]", fail)
        file = _text(r["file"], f"recordings[{i}].file", fail, empty=False)
        split = r.get("split", "train")
        if split not in SPLITS or not isinstance(split, str):
            raise fail(f"recordings[{i}] ({file!r}): split must be one of {SPLITS}, got {split!r}")
        recs.append(RecordingEntry(file, split))
    return recs
