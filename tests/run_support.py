"""A tiny dataset, recipe and trained bundle, shared by the CLI, bundle and data-safety tests."""

from __future__ import annotations

from pathlib import Path

from torchfilt.io.synth import simulate_dataset
from torchfilt.pipeline import train_recipe

RECIPE = """
name = "tiny"
seed = 3
[dataset]
path = "{data}"
[transition]
increment = true
iterations = {iters}
lr = 0.05
[measurement]
iterations = {iters}
lr = 0.05
[train]
checkpoint_every = {every}
[calibrate]
iterations = {cal_iters}
"""


def tiny_dataset(root: Path, recordings: int = 6, steps: int = 30) -> Path:
    """The reaction system's recordings (CSV) with a manifest, in ``root``."""
    simulate_dataset("reaction", root, recordings=recordings, steps=steps, seed=0)
    return root


def write_recipe(
    path: Path, data: Path, iters: int = 3, every: int = 1, extra: str = "", cal_iters: int = 5
) -> Path:
    """A recipe training both sides as GPs for ``iters`` iterations, then ``cal_iters`` of
    calibration."""
    text = RECIPE.format(data=data.as_posix(), iters=iters, every=every, cal_iters=cal_iters)
    path.write_text(text + extra)
    return path


def tiny_bundle(root: Path) -> Path:
    """Train a tiny GP bundle (a few seconds) and return ``model.pt``."""
    data = tiny_dataset(root / "data")
    recipe = write_recipe(root / "tiny.toml", data)
    return train_recipe(recipe, root / "run", progress=False)


def total_pressure(x):  # type: ignore[no-untyped-def]
    """A user's own sensor for entry-point recipes whose module every process (Ray actors
    included) can import: PA + PB, states ``(..., 2)`` -> ``(..., 1)``."""
    return x.sum(-1, keepdim=True)
