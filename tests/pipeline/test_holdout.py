"""The default hold-out of ``torchfilt train``: a dataset without validation recordings gets some
held out (whole recordings from 4 on, else the last part of each), the log says so, the
validation stage then has data; ``[train] holdout = 0`` turns it off and the log says early
stopping cannot act."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from torchfilt.exceptions import RecipeError
from torchfilt.io.synth import simulate_dataset
from torchfilt.pipeline import train_recipe

RECIPE = """
name = "holdout"
seed = 1
states = "none"
[dataset]
path = "{data}"
[measurement]
model = "system:reaction"
[filter]
prior = "system:reaction"
[measurement_only]
iterations = 1
inducing = 3
m_step_iterations = 2
[train]
{train}
[calibrate]
iterations = 2
"""


def _train_only(root: Path, recordings: int) -> Path:
    simulate_dataset("reaction", root, recordings=recordings, steps=40, seed=0)
    man = json.loads((root / "manifest.json").read_text())
    for rec in man["recordings"]:
        rec["split"] = "train"
    (root / "manifest.json").write_text(json.dumps(man))
    return root


def _run(tmp_path: Path, recordings: int, train: str = "") -> tuple[str, dict]:
    data = _train_only(tmp_path / "data", recordings)
    recipe = tmp_path / "r.toml"
    recipe.write_text(RECIPE.format(data=data.as_posix(), train=train))
    train_recipe(recipe, tmp_path / "run", progress=False)
    log = (tmp_path / "run" / "train.log").read_text()
    return log, json.loads((tmp_path / "run" / "validation.json").read_text())


def test_whole_recordings_are_held_out_by_default(tmp_path) -> None:
    log, val = _run(tmp_path, 5)
    assert "4 train / 1 validation recordings (held out by default" in log
    assert "holdout = 0 to change" in log
    assert "uncalibrated" in val["filter"]  # the validation stage had recordings


def test_few_recordings_hold_out_their_tails(tmp_path) -> None:
    log, val = _run(tmp_path, 2)
    assert "2 train recordings, their last 20% held out for validation" in log
    assert "uncalibrated" in val["filter"]


def test_holdout_zero_turns_it_off_and_says_early_stopping_cannot_act(tmp_path) -> None:
    log, val = _run(tmp_path, 5, "holdout = 0")
    assert "early stopping and model selection cannot act" in log
    assert "filter" not in val


def test_holdout_out_of_range_is_refused(tmp_path) -> None:
    with pytest.raises(RecipeError, match=r"\[train\] holdout must be a number in \[0, 0.5\]"):
        _run(tmp_path, 5, "holdout = 0.9")
