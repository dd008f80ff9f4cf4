"""A tiny dataset, recipe and trained bundle, shared by the CLI, bundle and data-safety tests;
and the pieces several pipeline tests share: a fit interrupted at an iteration, a user's sensor
module written for one test."""

from __future__ import annotations

import itertools
from collections.abc import Callable
from pathlib import Path
from typing import Any

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


def interrupted_at(fit: Callable[..., Any], iteration: int) -> Callable[..., Any]:
    """``fit`` (a stage's fit, called with a ``callback=``) that raises ``KeyboardInterrupt``, as
    a Ctrl-C would, once its callback has seen ``iteration``."""

    def interrupted(*args: Any, **kwargs: Any) -> Any:
        inner = kwargs["callback"]

        def cb(state: Any) -> None:
            inner(state)
            if state.iteration == iteration:
                raise KeyboardInterrupt

        return fit(*args, **{**kwargs, "callback": cb})

    return interrupted


_modules = itertools.count()


def sensor_module(folder: Path, source: str, prefix: str, monkeypatch: Any) -> tuple[str, Path]:
    """A fresh module ``source`` in ``folder/sensors`` on ``sys.path`` (a new name per call: no
    import cache between tests); its name and file."""
    name = f"{prefix}_{next(_modules)}"
    (folder / "sensors").mkdir()
    path = folder / "sensors" / f"{name}.py"
    path.write_text(source)
    monkeypatch.syspath_prepend(str(folder / "sensors"))
    return name, path
