"""The CLI's error contract: every user error exits 2 with one line on stderr and no traceback;
anything else (a bug) keeps its traceback."""

from __future__ import annotations

import errno
import json
import os
import time

import pytest
import torch
from run_support import tiny_bundle, write_recipe

from torchfilt.cli import main
from torchfilt.pipeline import load_bundle, load_recipe, save_bundle

#: ``--device cuda`` on a CPU build must fail before anything is loaded: well under this.
FAIL_FAST_S = 5.0


@pytest.fixture(scope="module")
def world(tmp_path_factory):
    """A dataset, a recipe, a trained bundle and a recording, shared by the matrix."""
    root = tmp_path_factory.mktemp("world")
    bundle = tiny_bundle(root)
    data = root / "data"
    return {
        "root": root,
        "data": data,
        "recipe": root / "tiny.toml",
        "bundle": bundle,
        "rec": data / "rec_005.csv",
    }


def run_cli(args: list[str], capsys) -> tuple[int, str]:
    capsys.readouterr()
    code = main([str(a) for a in args])
    return code, capsys.readouterr().err


def assert_one_line(code: int, err: str, *needles: str) -> None:
    assert code == 2, err
    assert "Traceback" not in err
    lines = err.strip().splitlines()
    assert len(lines) == 1, err
    for n in needles:
        assert n in lines[0], lines[0]


# ------------------------------------------------------------------------------ RunError cases
def test_existing_run_directory(world, tmp_path, capsys):
    run = tmp_path / "run"
    run.mkdir()
    (run / "config.json").write_text("{}")
    code, err = run_cli(["train", world["recipe"], "--out", run, "--quiet"], capsys)
    assert_one_line(code, err, "already holds a run", "--force")


def test_resume_in_empty_directory(world, tmp_path, capsys):
    code, err = run_cli(
        ["train", world["recipe"], "--out", tmp_path / "empty", "--resume", "--quiet"], capsys
    )
    assert_one_line(code, err, "no run to resume")
    assert not (tmp_path / "empty").exists(), "a failed resume creates no directory"


def test_resume_with_changed_recipe(world, tmp_path, capsys):
    run = tmp_path / "run"
    run.mkdir()
    (run / "config.json").write_text(json.dumps({"digest": "0" * 64}))
    code, err = run_cli(["train", world["recipe"], "--out", run, "--resume", "--quiet"], capsys)
    assert_one_line(code, err, "recipe changed")


def test_resume_with_changed_dataset(world, tmp_path, capsys):
    run = tmp_path / "run"
    run.mkdir()
    digest = load_recipe(world["recipe"]).digest()
    (run / "config.json").write_text(json.dumps({"digest": digest}))
    (run / "dataset.json").write_text(json.dumps({"fingerprint": {"dataset_sha256": "0" * 64}}))
    code, err = run_cli(["train", world["recipe"], "--out", run, "--resume", "--quiet"], capsys)
    assert_one_line(code, err, "dataset changed")


# ------------------------------------------------------------------------------ outputs
@pytest.mark.parametrize("command", ["filter", "simulate", "train"])
def test_out_is_a_file(world, tmp_path, capsys, command):
    target = tmp_path / "a_file"
    target.write_text("precious")
    args = {
        "filter": ["filter", "--model", "system:reaction", world["rec"], "--out", target],
        "simulate": ["simulate", "reaction", "--out", target, "--recordings", "2"],
        "train": ["train", world["recipe"], "--out", target, "--quiet"],
    }[command]
    code, err = run_cli(args, capsys)
    assert_one_line(code, err, str(target))
    assert target.read_text() == "precious"


@pytest.mark.parametrize(
    ("err_no", "needle"),
    [
        (errno.EACCES, "permission denied"),
        (errno.EROFS, "read-only"),
        (errno.ENOSPC, "no space left"),
    ],
)
@pytest.mark.parametrize("command", ["filter", "simulate"])
def test_unwritable_output(world, tmp_path, capsys, monkeypatch, err_no, needle, command):
    """A read-only folder or a full disk: simulated (the tests may run as root), at the write
    (``mkstemp`` for permissions, ``fsync`` for a full disk) as the OS would report it."""
    import tempfile

    def fail(*args, **kwargs):
        raise OSError(err_no, os.strerror(err_no))

    if err_no == errno.ENOSPC:
        monkeypatch.setattr(os, "fsync", fail)
    else:
        monkeypatch.setattr(tempfile, "mkstemp", fail)
    out = tmp_path / "out"
    args = {
        "filter": ["filter", "--model", "system:reaction", world["rec"], "--out", out],
        "simulate": ["simulate", "reaction", "--out", out, "--recordings", "2"],
    }[command]
    code, err = run_cli(args, capsys)
    assert_one_line(code, err, needle, str(out))


def test_full_disk_while_training(world, tmp_path, capsys, monkeypatch):
    def fail(*args, **kwargs):
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

    monkeypatch.setattr(os, "fsync", fail)
    code, err = run_cli(["train", world["recipe"], "--out", tmp_path / "run", "--quiet"], capsys)
    assert_one_line(code, err, "no space left")
    assert not (tmp_path / "run").exists(), "a failed first write leaves no run directory"


# ------------------------------------------------------------------------------ inputs
def test_csv_field_over_the_limit(world, tmp_path, capsys):
    bad = tmp_path / "huge.csv"
    lines = world["rec"].read_text().splitlines()
    row = lines[2].split(",")
    row[-1] = "1" * 140_000
    bad.write_text("\n".join([lines[0], lines[1], ",".join(row), *lines[3:]]) + "\n")
    code, err = run_cli(
        ["filter", "--model", "system:reaction", bad, "--out", tmp_path / "o"], capsys
    )
    assert_one_line(code, err, str(bad), "line 3", "field larger than field limit")


@pytest.mark.skipif(torch.cuda.is_available(), reason="needs a machine without CUDA")
def test_device_cuda_without_cuda_fails_fast(world, tmp_path, capsys):
    t0 = time.perf_counter()
    code, err = run_cli(
        [
            "filter",
            "--model",
            world["bundle"],
            world["rec"],
            "--out",
            tmp_path / "o",
            "--device",
            "cuda",
        ],
        capsys,
    )
    elapsed = time.perf_counter() - t0
    assert_one_line(code, err, "--device 'cuda'")
    assert elapsed < FAIL_FAST_S
    assert not (tmp_path / "o").exists(), "nothing is written before the device is checked"


def test_device_bogus(world, tmp_path, capsys):
    code, err = run_cli(
        [
            "filter",
            "--model",
            "system:reaction",
            world["rec"],
            "--out",
            tmp_path / "o",
            "--device",
            "bogus",
        ],
        capsys,
    )
    assert_one_line(code, err, "--device 'bogus'", "not a torch device")


def test_simulate_zero_steps(tmp_path, capsys):
    code, err = run_cli(["simulate", "reaction", "--out", tmp_path / "ds", "--steps", "0"], capsys)
    assert_one_line(code, err, "steps must be an integer >= 1")
    assert not (tmp_path / "ds").exists()


def test_empty_recording_list_fails_before_loading(world, tmp_path, capsys, monkeypatch):
    import torchfilt.pipeline.offline as offline

    def never(*args, **kwargs):
        raise AssertionError("the model was loaded before the recordings were checked")

    monkeypatch.setattr(offline, "resolve_model", never)
    with pytest.raises(Exception, match="no recordings given"):
        offline.filter_recordings(world["bundle"], [], tmp_path / "o")
    code, err = run_cli(
        ["filter", "--model", world["bundle"], tmp_path / "nope.csv", "--out", tmp_path / "o"],
        capsys,
    )
    assert_one_line(code, err, "recording not found")


@pytest.mark.parametrize("command", ["info", "filter"])
def test_bundle_with_a_tensor_shape_edited(world, tmp_path, capsys, command):
    b = load_bundle(world["bundle"])
    sd = b["transition"]["state"]["state_dict"]
    key = next(k for k in sd if k.endswith("raw_lengthscale"))
    sd[key] = torch.cat([sd[key], sd[key][..., :1]], -1)
    edited = save_bundle(tmp_path / "edited.pt", b)  # a valid checksum over edited content
    args = {
        "info": ["info", edited],
        "filter": ["filter", "--model", edited, world["rec"], "--out", tmp_path / "o"],
    }[command]
    code, err = run_cli(args, capsys)
    assert_one_line(code, err, str(edited), "malformed transition model", key)


def test_flipped_byte_bundle_is_one_line(world, tmp_path, capsys):
    raw = bytearray(world["bundle"].read_bytes())
    raw[len(raw) // 2] ^= 0x01
    bad = tmp_path / "flipped.pt"
    bad.write_bytes(bytes(raw))
    code, err = run_cli(["info", bad], capsys)
    assert_one_line(code, err, str(bad), "checksum mismatch")


def test_recipe_error_is_one_line(world, tmp_path, capsys):
    recipe = write_recipe(tmp_path / "bad.toml", world["data"])
    recipe.write_text(recipe.read_text().replace("[measurement]", "[measurement]\ninputs = ['B']"))
    code, err = run_cli(["train", recipe, "--out", tmp_path / "run", "--quiet"], capsys)
    assert_one_line(code, err, "unknown channel 'B'")


# ------------------------------------------------------------------------------ real bugs
def test_a_bug_keeps_its_traceback(tmp_path, monkeypatch):
    import torchfilt.io.synth as synth

    def bug(*args, **kwargs):
        raise ZeroDivisionError("a bug")

    monkeypatch.setattr(synth, "simulate_dataset", bug)
    with pytest.raises(ZeroDivisionError):
        main(["simulate", "reaction", "--out", str(tmp_path / "ds")])


def test_debug_shows_the_traceback(tmp_path):
    with pytest.raises(Exception, match="steps must be"):
        main(["--debug", "simulate", "reaction", "--out", str(tmp_path / "ds"), "--steps", "0"])
