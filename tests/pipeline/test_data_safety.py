"""Never lose data: unique outputs, no overwrite without --force, atomic writes with umask modes
and cleaned temporary files, run directories that a failed attempt does not block."""

from __future__ import annotations

import json
import os
import subprocess
import sys

import numpy as np
import pytest
from run_support import tiny_dataset, write_recipe

from torchfilt.cli import main
from torchfilt.exceptions import InputError, OutputError, RecipeError, RunError
from torchfilt.io import atomic_write_text, sha256_file
from torchfilt.io.atomic import clean_stale_temps
from torchfilt.io.estimates import read_estimates
from torchfilt.io.synth import simulate_dataset
from torchfilt.pipeline import evaluate_outputs, filter_recordings, train_recipe


@pytest.fixture(scope="module")
def two_datasets(tmp_path_factory):
    """Two folders whose recordings share their names (rec_000.csv, ...), different content."""
    root = tmp_path_factory.mktemp("two")
    simulate_dataset("reaction", root / "a", recordings=2, steps=15, seed=1)
    simulate_dataset("reaction", root / "b", recordings=2, steps=15, seed=2)
    return root


def snapshot(folder) -> dict[str, str]:
    return {p.name: sha256_file(p) for p in sorted(folder.iterdir()) if p.is_file()}


# ------------------------------------------------------------------------------ filter
def test_recordings_sharing_a_stem_keep_their_relative_path(two_datasets, tmp_path):
    a, b = two_datasets / "a" / "rec_000.csv", two_datasets / "b" / "rec_000.csv"
    assert sha256_file(a) != sha256_file(b)
    both = filter_recordings("system:reaction", [a, b], tmp_path / "both")
    assert [e["filtered"] for e in both["recordings"]] == [
        "a/rec_000.filtered.csv",
        "b/rec_000.filtered.csv",
    ]
    for rec, name in ((a, "a"), (b, "b")):
        alone = filter_recordings("system:reaction", [rec], tmp_path / f"only_{name}")
        got = read_estimates(tmp_path / "both" / name / "rec_000.filtered.csv")
        want = read_estimates(tmp_path / f"only_{name}" / alone["recordings"][0]["filtered"])
        np.testing.assert_array_equal(got.mean, want.mean)
    ev = evaluate_outputs(tmp_path / "both")
    for entry, name in zip(ev["recordings"], ("a", "b"), strict=True):
        solo = evaluate_outputs(tmp_path / f"only_{name}")["recordings"][0]
        assert entry["rmse"] == solo["rmse"]


def test_same_recording_twice_is_refused(two_datasets, tmp_path):
    a = two_datasets / "a" / "rec_000.csv"
    with pytest.raises(InputError, match="given twice"):
        filter_recordings("system:reaction", [a, a], tmp_path / "o")
    assert not (tmp_path / "o").exists()


def test_filter_refuses_to_overwrite_without_force(two_datasets, tmp_path, capsys):
    rec = str(two_datasets / "a" / "rec_001.csv")
    out = tmp_path / "o"
    assert main(["filter", "--model", "system:reaction", rec, "--out", str(out)]) == 0
    (out / "rec_001.filtered.csv").write_text("mine")
    before = snapshot(out)
    assert main(["filter", "--model", "system:reaction", rec, "--out", str(out)]) == 2
    assert "exists and would be overwritten" in capsys.readouterr().err
    assert snapshot(out) == before
    assert main(["filter", "--model", "system:reaction", rec, "--out", str(out), "--force"]) == 0
    assert (out / "rec_001.filtered.csv").read_text() != "mine"


def test_evaluate_refuses_to_overwrite_without_force(two_datasets, tmp_path):
    out = tmp_path / "o"
    filter_recordings("system:reaction", [two_datasets / "a" / "rec_000.csv"], out)
    evaluate_outputs(out)
    with pytest.raises(OutputError, match=r"evaluation_filtered\.json"):
        evaluate_outputs(out)
    evaluate_outputs(out, force=True)


# ------------------------------------------------------------------------------ simulate
def test_simulate_refuses_an_existing_dataset(tmp_path, capsys):
    ds = tmp_path / "ds"
    assert (
        main(["simulate", "reaction", "--out", str(ds), "--recordings", "4", "--steps", "5"]) == 0
    )
    before = snapshot(ds)
    assert main(["simulate", "pendulum", "--out", str(ds), "--recordings", "2"]) == 2
    err = capsys.readouterr().err
    assert "manifest.json: exists" in err and "--force" in err
    assert snapshot(ds) == before
    args = ["simulate", "reaction", "--out", str(ds), "--recordings", "2", "--steps", "5"]
    assert main([*args, "--force", "--seed", "7"]) == 0
    manifest = json.loads((ds / "manifest.json").read_text())
    listed = {r["file"] for r in manifest["recordings"]}
    assert listed == {"rec_000.csv", "rec_001.csv"}
    assert {p.name for p in ds.iterdir()} == listed | {"manifest.json"}, "no orphans"


# ------------------------------------------------------------------------------ atomic writes
@pytest.mark.parametrize(("umask", "mode"), [(0o022, 0o644), (0o077, 0o600), (0o002, 0o664)])
def test_written_files_follow_the_umask(tmp_path, umask, mode):
    old = os.umask(umask)
    try:
        p = atomic_write_text(tmp_path / "x.txt", "hello")
    finally:
        os.umask(old)
    assert p.stat().st_mode & 0o777 == mode


def _dead_pid() -> int:
    proc = subprocess.Popen([sys.executable, "-c", "pass"])
    proc.wait()
    return proc.pid


def test_temp_files_of_a_killed_write_are_cleaned(tmp_path):
    stale = tmp_path / f".model.pt.{_dead_pid()}.abc123.tmp"
    live = tmp_path / f".model.pt.{os.getpid()}.def456.tmp"
    other = tmp_path / ".notes.tmp"
    for p in (stale, live, other):
        p.write_bytes(b"partial")
    atomic_write_text(tmp_path / "model.pt", "new")
    assert not stale.exists()
    assert live.exists() and other.exists()
    assert clean_stale_temps(tmp_path / "missing") == []


def test_a_killed_write_leaves_the_old_file_and_a_temp_the_next_run_removes(tmp_path):
    """A real kill: a child process is SIGKILLed inside the write callback."""
    target = tmp_path / "data.txt"
    target.write_text("old")
    code = (
        "import os, signal\n"
        "from torchfilt.io import atomic_write\n"
        "def write(fh):\n"
        "    fh.write(b'half')\n"
        "    fh.flush()\n"
        "    os.kill(os.getpid(), signal.SIGKILL)\n"
        f"atomic_write({str(target)!r}, write)\n"
    )
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(sys.path)}
    proc = subprocess.run([sys.executable, "-c", code], env=env, check=False)
    assert proc.returncode == -9
    temps = [p for p in tmp_path.iterdir() if p.name.endswith(".tmp")]
    assert len(temps) == 1 and target.read_text() == "old"
    atomic_write_text(tmp_path / "other.txt", "x")  # the next write into the folder
    assert not any(p.name.endswith(".tmp") for p in tmp_path.iterdir())


# ------------------------------------------------------------------------------ training runs
@pytest.fixture(scope="module")
def data(tmp_path_factory):
    return tiny_dataset(tmp_path_factory.mktemp("train"), recordings=5, steps=20)


def test_recipe_channel_error_before_training_leaves_no_run(data, tmp_path, monkeypatch):
    from torchfilt.models.gp import GPTransition

    def never(*args, **kwargs):
        raise AssertionError("trained before the recipe was checked")

    monkeypatch.setattr(GPTransition, "fit", never)
    recipe = write_recipe(tmp_path / "r.toml", data)
    recipe.write_text(recipe.read_text().replace("[measurement]", "[measurement]\ninputs = ['B']"))
    run = tmp_path / "run"
    with pytest.raises(RecipeError, match=r"\[measurement\] inputs: unknown channel 'B'"):
        train_recipe(recipe, run, progress=False)
    assert not run.exists()


def test_failure_before_any_stage_does_not_block_the_next_attempt(data, tmp_path):
    recipe = write_recipe(tmp_path / "r.toml", data)
    # a value only the fit checks: the run directory exists when it fails
    recipe.write_text(recipe.read_text().replace("[transition]", "[transition]\nnoise = -1.0"))
    run = tmp_path / "run"
    run.mkdir()
    (run / "notes.txt").write_text("mine")
    with pytest.raises(ValueError, match="noise"):
        train_recipe(recipe, run, progress=False)
    assert {p.name for p in run.iterdir()} == {"notes.txt"}
    write_recipe(recipe, data)
    assert train_recipe(recipe, run, progress=False).is_file()
    assert (run / "notes.txt").read_text() == "mine"


def test_force_discards_the_old_run_only(data, tmp_path):
    recipe = write_recipe(tmp_path / "r.toml", data)
    run = tmp_path / "run"
    train_recipe(recipe, run, progress=False)
    (run / "notes.txt").write_text("mine")
    with pytest.raises(RunError, match="--force"):
        train_recipe(recipe, run, progress=False)
    with pytest.raises(InputError, match="pick one"):
        train_recipe(recipe, run, resume=True, force=True, progress=False)
    write_recipe(recipe, data, iters=4)
    train_recipe(recipe, run, force=True, progress=False)
    lines = (run / "metrics.jsonl").read_text().splitlines()
    gp_lines = [ln for ln in lines if '"calibrate"' not in ln]
    assert len(gp_lines) == 8 and (run / "notes.txt").read_text() == "mine"


def test_torn_metrics_line_does_not_block_resume(data, tmp_path):
    recipe = write_recipe(tmp_path / "r.toml", data)
    run = tmp_path / "run"
    train_recipe(recipe, run, progress=False)
    metrics = run / "metrics.jsonl"
    good = metrics.read_text()
    metrics.write_text(good + '{"stage": "measurement", "itera')  # killed mid-line
    train_recipe(recipe, run, resume=True, progress=False)
    assert metrics.read_text() == good
    lines = good.splitlines()
    metrics.write_text("\n".join([lines[0], "garbage", *lines[1:]]) + "\n")
    with pytest.raises(RunError, match=r"metrics\.jsonl: line 2 is not a metrics record"):
        train_recipe(recipe, run, resume=True, progress=False)
