"""Recordings and datasets: round trips, fingerprints, and every validation error with its message."""

import json

import numpy as np
import pytest

from torchfilt.io import (
    Channel,
    DataError,
    Manifest,
    Recording,
    RecordingEntry,
    load_dataset,
    read_recording,
    write_recording,
)
from torchfilt.io.atomic import atomic_write

CHANNELS = (
    Channel("alt", "state", "ft"),
    Channel("vel", "state", "ft/s"),
    Channel("thrust", "input", "N"),
    Channel("range", "measurement", "ft"),
)


def make_recording(T=20, seed=0, missing=True):
    rng = np.random.default_rng(seed)
    t = np.arange(T) * 0.5
    cols = {c.name: rng.standard_normal(T) for c in CHANNELS}
    if missing:
        cols["range"][::3] = np.nan
    return Recording.from_arrays(t, CHANNELS, cols)


def make_dataset(tmp_path, n=4, fmt=".csv"):
    entries = []
    for i in range(n):
        f = f"rec{i}{fmt}"
        write_recording(make_recording(seed=i), tmp_path / f)
        entries.append(RecordingEntry(f, "train" if i < n - 1 else "validation"))
    m = Manifest("toy", 0.5, CHANNELS, tuple(entries))
    m.save(tmp_path / "manifest.json")
    return m


@pytest.mark.parametrize("fmt", [".csv", ".npz"])
def test_round_trip_is_exact(tmp_path, fmt):
    rec = make_recording()
    write_recording(rec, tmp_path / f"r{fmt}")
    back = read_recording(tmp_path / f"r{fmt}", CHANNELS, sample_time=0.5)
    np.testing.assert_array_equal(back.time, rec.time)
    np.testing.assert_array_equal(back.data, rec.data)  # NaN positions included
    assert back.states.shape == (20, 2) and back.inputs.shape == (20, 1)
    assert back.measurements.isnan().sum() == 7


def test_dataset_splits_fingerprint_statistics(tmp_path):
    make_dataset(tmp_path)
    ds = load_dataset(tmp_path)
    assert [r.name for r in ds.split("train")] == ["rec0", "rec1", "rec2"]
    assert [r.name for r in ds.split("validation")] == ["rec3"]
    fp = ds.fingerprint()
    assert set(fp["files"]) == {"rec0.csv", "rec1.csv", "rec2.csv", "rec3.csv"}
    assert fp["files"]["rec0.csv"]["rows"] == 20
    stats = ds.statistics("train")
    alt = np.concatenate([r.column("alt") for r in ds.split("train")])
    assert stats["alt"]["mean"] == pytest.approx(alt.mean())
    assert stats["range"]["missing"] == 21
    # the fingerprint is stable, and changes when a file changes
    assert load_dataset(tmp_path).fingerprint() == fp
    rec = make_recording(seed=99)
    write_recording(rec, tmp_path / "rec1.csv")
    fp2 = load_dataset(tmp_path).fingerprint()
    assert fp2["dataset_sha256"] != fp["dataset_sha256"]
    assert fp2["files"]["rec0.csv"] == fp["files"]["rec0.csv"]
    log = ds.log()
    assert log["split"]["validation"] == ["rec3"] and "train" in log["statistics"]


def test_missing_column_names_file_column_and_suggests(tmp_path):
    rec = make_recording()
    write_recording(rec, tmp_path / "r.csv")
    text = (tmp_path / "r.csv").read_text().replace("range", "rnage", 1)
    (tmp_path / "r.csv").write_text(text)
    with pytest.raises(
        DataError, match=r"r\.csv, column 'range', line 1: missing column.*did you mean 'rnage'"
    ):
        read_recording(tmp_path / "r.csv", CHANNELS)


def test_missing_array_in_npz(tmp_path):
    np.savez(tmp_path / "r.npz", time=np.arange(3.0), alt=np.zeros(3))
    with pytest.raises(DataError, match=r"column 'vel'.*missing array"):
        read_recording(tmp_path / "r.npz", CHANNELS)


def test_non_monotonic_time_names_line(tmp_path):
    rec = make_recording()
    rec.time[5] = rec.time[4]
    write_recording(rec, tmp_path / "r.csv")
    with pytest.raises(DataError, match=r"column 'time', line 7: time is not strictly increasing"):
        read_recording(tmp_path / "r.csv", CHANNELS)


def test_time_step_off_sample_time(tmp_path):
    write_recording(make_recording(), tmp_path / "r.csv")
    with pytest.raises(
        DataError, match=r"line 3: time step 0.5 differs from the manifest's sample_time 1"
    ):
        read_recording(tmp_path / "r.csv", CHANNELS, sample_time=1.0)


def test_nan_in_training_states_names_column_and_line(tmp_path):
    make_dataset(tmp_path)
    rec = make_recording(seed=1)
    rec.data[4, 1] = np.nan  # vel
    write_recording(rec, tmp_path / "rec1.csv")
    with pytest.raises(
        DataError, match=r"rec1\.csv, column 'vel', line 6: state channels of training data"
    ):
        load_dataset(tmp_path)
    # the same file is fine as a test recording (no truth needed to filter it)
    m = json.loads((tmp_path / "manifest.json").read_text())
    m["recordings"][1]["split"] = "test"
    (tmp_path / "manifest.json").write_text(json.dumps(m))
    assert len(load_dataset(tmp_path).split("test")) == 1


def test_nan_input_rejected_for_training(tmp_path):
    rec = make_recording()
    rec.data[2, 2] = np.nan
    write_recording(rec, tmp_path / "r.npz")
    with pytest.raises(DataError, match=r"column 'thrust', row 2: input channels"):
        read_recording(tmp_path / "r.npz", CHANNELS, require_finite=("state", "input"))


def test_dimension_mismatch_with_model(tmp_path):
    make_dataset(tmp_path)
    ds = load_dataset(tmp_path)
    ds.check_dims(state_dim=2, obs_dim=1, input_dim=1)
    with pytest.raises(
        DataError,
        match=r"manifest\.json: the model has 3 states but the manifest declares 2 state channels \['alt', 'vel'\]",
    ):
        ds.check_dims(state_dim=3)


def test_file_not_what_its_extension_says(tmp_path):
    write_recording(make_recording(), tmp_path / "a.npz")
    (tmp_path / "fake.csv").write_bytes((tmp_path / "a.npz").read_bytes())
    with pytest.raises(DataError, match=r"fake\.csv: is a zip/NPZ archive, not a CSV file"):
        read_recording(tmp_path / "fake.csv", CHANNELS)
    (tmp_path / "fake.npz").write_text("time,alt\n0,1\n")
    with pytest.raises(DataError, match=r"fake\.npz: is not an NPZ \(zip\) archive"):
        read_recording(tmp_path / "fake.npz", CHANNELS)
    (tmp_path / "bin.csv").write_bytes(b"\x00\x01\x02garbage")
    with pytest.raises(DataError, match="binary data, not CSV"):
        read_recording(tmp_path / "bin.csv", CHANNELS)
    (tmp_path / "r.txt").write_text("x")
    with pytest.raises(DataError, match=r"unsupported file type '\.txt'"):
        read_recording(tmp_path / "r.txt", CHANNELS)


def test_corrupt_and_pickled_npz_are_refused(tmp_path):
    write_recording(make_recording(), tmp_path / "a.npz")
    raw = (tmp_path / "a.npz").read_bytes()
    (tmp_path / "trunc.npz").write_bytes(raw[: len(raw) // 2])
    with pytest.raises(DataError, match=r"trunc\.npz: is not a readable NPZ archive"):
        read_recording(tmp_path / "trunc.npz", CHANNELS)
    arrays = {c.name: np.zeros(3) for c in CHANNELS}
    np.savez(tmp_path / "obj.npz", time=np.array([0.0, 1.0, object()], dtype=object), **arrays)
    with pytest.raises(DataError, match=r"obj\.npz: cannot be read safely"):
        read_recording(tmp_path / "obj.npz", CHANNELS)


def test_unparsable_value_and_ragged_row(tmp_path):
    write_recording(make_recording(), tmp_path / "r.csv")
    lines = (tmp_path / "r.csv").read_text().splitlines()
    lines[3] = lines[3].replace(lines[3].split(",")[1], "abc", 1)
    (tmp_path / "r.csv").write_text("\n".join(lines) + "\n")
    with pytest.raises(DataError, match=r"column 'alt', line 4: cannot read 'abc' as a number"):
        read_recording(tmp_path / "r.csv", CHANNELS)
    lines[3] = "1.5,2"
    (tmp_path / "r.csv").write_text("\n".join(lines) + "\n")
    with pytest.raises(DataError, match="line 4: has 2 fields, the header has 5"):
        read_recording(tmp_path / "r.csv", CHANNELS)


@pytest.mark.parametrize(
    ("patch", "message"),
    [
        ({"channels": [{"name": "a", "role": "sensor"}]}, "role must be one of"),
        ({"schema": "other/9"}, "unknown manifest schema"),
        ({"sample_time": -1}, "sample_time must be a finite positive number"),
        ({"sample_time": float("inf")}, "sample_time must be a finite positive number"),
        ({"sample_time": float("nan")}, "sample_time must be a finite positive number"),
        (
            {"channels": [{"name": "a", "role": "state"}, {"name": "a", "role": "input"}]},
            "duplicate column",
        ),
        ({"recordings": [{"file": "x.csv", "split": "dev"}]}, "split must be one of"),
        # issue 24: JSON types are checked, not converted with str()
        ({"recordings": [{"file": ["a.csv"]}]}, r"recordings\[0\]\.file must be a string"),
        ({"recordings": "a.csv"}, "recordings must be a list"),
        ({"channels": [{"name": 3, "role": "state"}]}, r"channels\[0\]\.name must be a string"),
        ({"channels": [{"name": "a", "role": 1}]}, r"channels\[0\] \('a'\): role must be one of"),
        ({"channels": [{"name": "a", "role": "state", "unit": 2}]}, r"channels\[0\]\.unit"),
        (
            {"channels": [{"name": "a", "role": "state", "units": "m"}]},
            r"unknown key\(s\) \['units'\]",
        ),
        ({"time": "t"}, "time must be an object"),
        ({"sample_time": "0.5"}, "sample_time must be a number"),
    ],
)
def test_manifest_errors(tmp_path, patch, message):
    base = {"name": "d", "sample_time": 1.0, "channels": [{"name": "a", "role": "state"}]}
    (tmp_path / "manifest.json").write_text(json.dumps({**base, **patch}))
    with pytest.raises(DataError, match=message):
        Manifest.load(tmp_path / "manifest.json")


def test_manifest_not_json(tmp_path):
    (tmp_path / "manifest.json").write_bytes(b"\x89PNG....")
    with pytest.raises(DataError, match="not a JSON manifest"):
        load_dataset(tmp_path)


def test_atomic_write_leaves_old_file_on_failure(tmp_path):
    target = tmp_path / "f.bin"
    target.write_bytes(b"old")

    def boom(fh):
        fh.write(b"partial")
        raise RuntimeError("interrupted")

    with pytest.raises(RuntimeError):
        atomic_write(target, boom)
    assert target.read_bytes() == b"old"
    assert [p.name for p in tmp_path.iterdir()] == ["f.bin"]


@pytest.mark.parametrize("fmt", [".csv", ".npz"])
def test_optional_roles_may_be_absent(tmp_path, fmt):
    meas_only = (Channel("thrust", "input"), Channel("range", "measurement"))
    rec = make_recording()
    sub = Recording.from_arrays(
        rec.time, meas_only, {c.name: rec.column(c.name) for c in meas_only}
    )
    write_recording(sub, tmp_path / f"r{fmt}")
    back = read_recording(tmp_path / f"r{fmt}", CHANNELS, optional=("state",))
    assert back.states.isnan().all() and not back.inputs.isnan().any()
    with pytest.raises(DataError, match="column 'alt'"):
        read_recording(tmp_path / f"r{fmt}", CHANNELS)


def test_estimates_round_trip(tmp_path):
    from torchfilt.io.estimates import Estimates, read_estimates, write_estimates

    rng = np.random.default_rng(0)
    A = rng.standard_normal((5, 3, 3))
    cov = A @ A.transpose(0, 2, 1) + np.eye(3)
    cov[2, 1, :] = cov[2, :, 1] = 0.0  # a zero-variance state: correlation undefined
    est = Estimates(
        np.arange(5.0), rng.standard_normal((5, 3)), cov, ["a", "b", "c"], rng.random(5), np.ones(5)
    )
    write_estimates(tmp_path / "e.csv", est)
    back = read_estimates(tmp_path / "e.csv")
    assert back.state_names == ["a", "b", "c"]
    np.testing.assert_allclose(back.cov, cov, rtol=1e-12, atol=1e-15)
    np.testing.assert_array_equal(back.mean, est.mean)
    np.testing.assert_array_equal(back.nis, est.nis)
    (tmp_path / "bad.csv").write_text("x,y\n1,2\n")
    with pytest.raises(DataError, match="not an estimates file"):
        read_estimates(tmp_path / "bad.csv")


# ------------------------------------------------------------------ non-finite and odd values
def _with_cell(tmp_path, line: int, column: int, value: str, blank_after_header: int = 0):
    """r.csv with one cell replaced (``line`` counts the header as 1) and blank lines inserted."""
    write_recording(make_recording(), tmp_path / "r.csv")
    lines = (tmp_path / "r.csv").read_text().splitlines()
    fields = lines[line - 1].split(",")
    fields[column] = value
    lines[line - 1] = ",".join(fields)
    lines[1:1] = [""] * blank_after_header
    (tmp_path / "r.csv").write_text("\n".join(lines) + "\n")
    return tmp_path / "r.csv"


@pytest.mark.parametrize("value", ["inf", "-inf", "Infinity", "1e999", "-1e400"])
def test_infinite_csv_cell_is_an_error_naming_file_line_column(tmp_path, value):
    path = _with_cell(tmp_path, 5, 4, value)
    with pytest.raises(
        DataError, match=rf"r\.csv, column 'range', line 5: '{value}' is not a finite"
    ):
        read_recording(path, CHANNELS)


@pytest.mark.parametrize("value", ["", "nan", "NaN", "NA"])
def test_missing_csv_cells_read_as_nan(tmp_path, value):
    rec = read_recording(_with_cell(tmp_path, 5, 4, value), CHANNELS)
    assert np.isnan(rec.column("range")[3])


def test_csv_line_numbers_count_blank_lines(tmp_path):
    path = _with_cell(tmp_path, 5, 1, "abc", blank_after_header=3)
    with pytest.raises(DataError, match=r"column 'alt', line 8: cannot read 'abc'"):
        read_recording(path, CHANNELS)
    write_recording(make_recording(), tmp_path / "t.csv")
    lines = (tmp_path / "t.csv").read_text().splitlines()
    lines[4] = lines[4].replace(lines[4].split(",")[0], "0", 1)  # time goes back at data row 4
    lines[1:1] = ["", ""]
    (tmp_path / "t.csv").write_text("\n".join(lines) + "\n")
    with pytest.raises(DataError, match=r"column 'time', line 7: time is not strictly increasing"):
        read_recording(tmp_path / "t.csv", CHANNELS)


def test_csv_field_over_the_limit_is_a_data_error(tmp_path):
    path = _with_cell(tmp_path, 3, 2, "7" * 200_000)
    with pytest.raises(DataError, match=r"line 3: unreadable CSV \(field larger than field limit"):
        read_recording(path, CHANNELS)


def _npz(tmp_path, **overrides):
    rec = make_recording()
    arrays = {"time": rec.time, **{c.name: rec.data[:, i] for i, c in enumerate(CHANNELS)}}
    arrays.update(overrides)
    np.savez(tmp_path / "r.npz", **arrays)
    return tmp_path / "r.npz"


def test_infinite_npz_value_is_an_error_naming_row(tmp_path):
    vel = make_recording().column("vel").copy()
    vel[6] = np.inf
    with pytest.raises(DataError, match=r"column 'vel', row 6: is not a finite number"):
        read_recording(_npz(tmp_path, vel=vel), CHANNELS)


def test_complex_npz_is_refused(tmp_path):
    rng = make_recording().column("range")
    with pytest.raises(DataError, match=r"column 'range': is complex"):
        read_recording(_npz(tmp_path, range=rng + 1j * rng), CHANNELS)


def test_manifest_infinity_literal_is_refused(tmp_path):
    text = '{"name": "d", "sample_time": Infinity, "channels": [{"name": "a", "role": "state"}]}'
    (tmp_path / "manifest.json").write_text(text)
    with pytest.raises(DataError, match="sample_time must be a finite positive number, got inf"):
        Manifest.load(tmp_path / "manifest.json")
