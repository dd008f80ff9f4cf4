"""Hypothesis suites over read_recording / write_recording (issue 12): random channels, times and
values (NaN = not observed) round-trip exactly through CSV and NPZ, or are refused with a DataError;
and over Manifest.from_dict (issue 24): a malformed manifest (a value of the wrong JSON type, a
missing or unknown key, an invalid role, split or sample time) is a DataError naming the key, and a
valid one gives exactly the manifest that was written. See tests/fuzz_support.py for the
contract."""

from __future__ import annotations

import math
import tempfile
from pathlib import Path

import numpy as np
import pytest
from fuzz_support import Refused, attempt, print_stats, property_tests
from hypothesis import strategies as st

from torchfilt.exceptions import DataError
from torchfilt.io import (
    Channel,
    Manifest,
    Recording,
    RecordingEntry,
    read_recording,
    write_recording,
)

_NAMES = st.text(alphabet="abcdefghijklmnopqrstuvwxyz_0123456789", min_size=1, max_size=8)
_VALUES = st.floats(allow_nan=True, allow_infinity=False, width=64)


def _round_trip(data: st.DataObject, values, name: str) -> None:
    names = data.draw(
        st.lists(_NAMES.filter(lambda s: s != "time"), min_size=1, max_size=4, unique=True),
        label="names",
    )
    roles = [data.draw(st.sampled_from(["state", "input", "measurement"])) for _ in names]
    channels = [Channel(nm, r) for nm, r in zip(names, roles, strict=True)]
    T = data.draw(st.integers(1, 6), label="T")
    steps = data.draw(st.lists(st.floats(1e-6, 1e6), min_size=T, max_size=T), label="steps")
    t0 = data.draw(st.floats(-1e6, 1e6), label="t0")
    time = t0 + np.cumsum(steps)
    cols = {nm: np.array(data.draw(st.lists(values, min_size=T, max_size=T))) for nm in names}
    rec, _ = attempt(f"Recording.from_arrays ({name})", Recording.from_arrays, time, channels, cols)
    if isinstance(rec, Refused):
        # only a time axis that round-off made non-increasing may be refused
        assert not np.all(np.diff(time) > 0), rec
        return
    suffix = data.draw(st.sampled_from([".csv", ".npz"]), label="suffix")
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / f"rec{suffix}"
        out, _ = attempt(f"write_recording ({name})", write_recording, rec, path)
        if isinstance(out, Refused):
            return
        back, _ = attempt(f"read_recording ({name})", read_recording, path, channels)
    assert not isinstance(back, Refused), back
    np.testing.assert_array_equal(back.time, rec.time)
    # exact, NaN in the same places, and inf (if accepted at all) kept as inf
    np.testing.assert_array_equal(back.data, rec.data)
    assert [c.name for c in back.channels] == names


def check_io(data: st.DataObject) -> None:
    _round_trip(data, _VALUES, "finite and NaN")


test_fuzz_io, test_fuzz_io_long = property_tests(check_io, short=6, long=400)


@pytest.mark.parametrize(
    "suffix",
    [
        ".csv",
        ".npz",
    ],
)
def test_infinite_value_round_trip(suffix, tmp_path):
    """Found by the fuzz suite: an inf is kept, or refused with a DataError, never turned to NaN."""
    ch = [Channel("a", "measurement")]
    rec = Recording.from_arrays(np.arange(3.0), ch, {"a": np.array([1.0, np.inf, -np.inf])})
    out, _ = attempt("write_recording (inf)", write_recording, rec, tmp_path / f"r{suffix}")
    if isinstance(out, Refused):
        return
    back, _ = attempt("read_recording (inf)", read_recording, out, ch)
    if isinstance(back, Refused):
        return
    np.testing.assert_array_equal(back.data, rec.data)


# -------------------------------------------------------------------------------------- manifest
#: Values that are not strings, for the keys that hold one.
_NOT_TEXT = [0, 1.5, True, None, [], ["a.csv"], {}, {"file": "a.csv"}]
#: Invalid values per kind of key (besides a non-string for a string key).
_INVALID = {
    "text": _NOT_TEXT,
    "word": [*_NOT_TEXT, ""],  # a non-empty name
    "role": [*_NOT_TEXT, "sensor", "State"],
    "split": [*_NOT_TEXT, "dev", ""],
    "sample_time": [*_NOT_TEXT, "0.1", -1.0, 0.0, math.nan, math.inf],
    "time": [0, "s", [], None, True],
    "channels": [0, "a", {}, None, [], [0], ["a"], [None]],
    "recordings": [0, "a.csv", {}, None, True, {"file": "a.csv"}, [3], [None], [[]]],
    "channel": [
        "a",
        3,
        None,
        {"name": "ZZ"},
        {"role": "state"},
        {"name": "ZZ", "role": "state", "x": 1},
    ],
    "recording": [3, None, {"split": "test"}, {"file": "x.csv", "y": 1}, ["a.csv"]],
}


def _valid_manifest(data: st.DataObject) -> tuple[dict, Manifest]:
    """A valid manifest dictionary and the Manifest it describes (built here, independently)."""
    time_name = data.draw(st.sampled_from(["time", "t"]), label="time name")
    names = data.draw(
        st.lists(
            _NAMES.filter(lambda s: s not in ("time", "t")), min_size=1, max_size=4, unique=True
        )
    )
    channels, given = [], []
    for nm in names:
        role = data.draw(st.sampled_from(["state", "input", "measurement"]))
        unit = data.draw(st.sampled_from([None, "", "m", "m/s"]), label="unit")
        given.append({"name": nm, "role": role, **({} if unit is None else {"unit": unit})})
        channels.append(Channel(nm, role, unit or ""))
    files = data.draw(st.lists(st.sampled_from(["a.csv", "b.npz", "c/d.csv"]), unique=True))
    recs, entries = [], []
    for f in files:
        split = data.draw(st.sampled_from([None, "train", "validation", "test"]), label="split")
        as_str = split is None and data.draw(st.booleans(), label="as a string")
        recs.append(f if as_str else {"file": f, **({} if split is None else {"split": split})})
        entries.append(RecordingEntry(f, split or "train"))
    dt = data.draw(st.floats(1e-3, 1e3) | st.integers(1, 10), label="sample_time")
    d = {
        "name": data.draw(_NAMES, label="name"),
        "sample_time": dt,
        "time": {"name": time_name, "unit": "s"},
        "channels": given,
        "recordings": recs,
        "description": "",
    }
    extra = {"generator": {"seed": 1}} if data.draw(st.booleans(), label="extra") else {}
    d.update(extra)
    want = Manifest(
        d["name"], float(dt), tuple(channels), tuple(entries), time_name, "s", "", extra
    )
    return d, want


def _mutate(data: st.DataObject, d: dict) -> list[str]:
    """Make ``d`` invalid at one key; return the names a message may use for that key."""
    ch, recs = d["channels"], d["recordings"]
    for i, r in enumerate(recs):
        if isinstance(r, str):
            recs[i] = {"file": r}
    # (object, key, kind of value, names for the message)
    sites: list[tuple[dict | list, str | int, str, list[str]]] = [
        (d, "name", "text", ["name"]),
        (d, "description", "text", ["description"]),
        (d, "sample_time", "sample_time", ["sample_time"]),
        (d, "time", "time", ["time"]),
        (d["time"], "name", "word", ["time.name"]),
        (d["time"], "unit", "text", ["time.unit"]),
        (d, "channels", "channels", ["channels"]),
        (d, "recordings", "recordings", ["recordings"]),
    ]
    for i, c in enumerate(ch):
        where = f"channels[{i}]"
        sites += [(ch, i, "channel", [where]), (c, "name", "word", [f"{where}.name"])]
        sites += [(c, "role", "role", [where]), (c, "unit", "text", [f"{where}.unit"])]
    for i, r in enumerate(recs):
        where = f"recordings[{i}]"
        sites += [(recs, i, "recording", [where]), (r, "file", "word", [f"{where}.file"])]
        sites += [(r, "split", "split", [where])]
    how = data.draw(st.sampled_from(["value", "value", "value", "missing", "unknown"]))
    if how == "missing":
        key = data.draw(st.sampled_from(["name", "sample_time", "channels"]), label="missing")
        del d[key]
        return [key]
    if how == "unknown":
        obj, where = data.draw(
            st.sampled_from(
                [(d["time"], "time"), *((c, f"channels[{i}]") for i, c in enumerate(ch))]
            )
        )
        obj["units"] = "s"
        return [where]
    obj, key, kind, names = data.draw(st.sampled_from(sites), label="site")
    obj[key] = data.draw(st.sampled_from(_INVALID[kind]), label="invalid value")  # type: ignore[index]
    return names


def check_manifest(data: st.DataObject) -> None:
    d, want = _valid_manifest(data)
    broken = data.draw(st.booleans(), label="broken")
    names = _mutate(data, d) if broken else []
    got, _ = attempt("Manifest.from_dict", Manifest.from_dict, d, path="m.json")
    if isinstance(got, Refused):
        assert broken, got
        assert isinstance(got.error, DataError), got
        assert str(got.error).startswith("m.json: "), got
        assert any(n in str(got.error) for n in names), (got, names)
        return
    assert not broken, f"accepted a manifest broken at {names}: {d!r}"
    assert got == want
    assert Manifest.from_dict(got.to_dict()) == got


test_fuzz_manifest, test_fuzz_manifest_long = property_tests(check_manifest, short=100, long=600)


def teardown_module() -> None:
    print_stats()
