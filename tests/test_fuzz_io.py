"""Hypothesis suite over read_recording / write_recording (issue 12): random channels, times and
values (NaN = not observed) round-trip exactly through CSV and NPZ, or are refused with a DataError.
See tests/fuzz_support.py for the contract."""

from __future__ import annotations

import tempfile
from pathlib import Path

import numpy as np
import pytest
from fuzz_support import Refused, attempt, print_stats, property_tests
from hypothesis import strategies as st

from torchfilt.io import Channel, Recording, read_recording, write_recording

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


def teardown_module() -> None:
    print_stats()
