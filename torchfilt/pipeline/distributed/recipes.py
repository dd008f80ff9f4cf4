"""Training several recipes, or one recipe over several datasets, as parallel Ray tasks
(``torchfilt train A.toml B.toml --ray``)."""

from __future__ import annotations

import dataclasses
import os
import sys
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any, TextIO

from torchfilt.exceptions import InputError, RunError
from torchfilt.io.atomic import output_dir
from torchfilt.pipeline.distributed.session import _one_line, import_ray, ray_session
from torchfilt.pipeline.recipe import Recipe, load_recipe
from torchfilt.pipeline.run import train_recipe

__all__ = ["train_recipes_ray"]


def _train_one(recipe: Recipe, out: str, resume: bool, force: bool) -> dict[str, Any]:
    t0 = time.perf_counter()
    bundle = train_recipe(recipe, out, resume=resume, force=force, progress=False)
    return {"bundle": str(bundle), "seconds": time.perf_counter() - t0}


def train_recipes_ray(
    recipes: Sequence[str | Path | Recipe],
    out: str | Path,
    *,
    datasets: Sequence[str | Path] | None = None,
    address: str | None = None,
    workers: int | None = None,
    resume: bool = False,
    force: bool = False,
    max_retries: int = 0,
    stream: TextIO | None = None,
) -> dict[str, Path]:
    """Train several models as parallel Ray tasks, one run directory each under ``out``.

    Either several recipes (run directory ``out/{recipe name}``), or one recipe over several
    ``datasets`` (one model per unit: ``out/{dataset folder name}``, the recipe with its
    ``[dataset] path`` replaced). Each task is :func:`~torchfilt.pipeline.train_recipe`, so each
    run has its own checkpoints; ``resume`` continues every run from its checkpoint (a run
    already finished is not retrained).

    Args:
        recipes: recipe files or :class:`Recipe` objects.
        out: parent folder of the run directories.
        datasets: with one recipe, the datasets to train it on.
        address: Ray cluster (see :func:`ray_session`).
        workers: CPUs of a new local instance.
        resume: continue the runs in the run directories.
        force: discard runs already in the run directories.
        max_retries: times Ray reruns a task whose worker died (a rerun resumes from the
            checkpoint).
        stream: where progress lines go (default ``sys.stderr``).

    Returns:
        The model bundle of each unit, by run name.

    Raises:
        MissingDependencyError: Ray is not installed.
        InputError: no recipes, ``datasets`` with several recipes, a dataset that does not exist,
            two units with one run name.
        RecipeError: an invalid recipe (checked here, before any task starts).
        RunError: some runs failed, including on an invalid dataset or a run directory that
            already holds a run (each task checks its own before it trains, as
            :func:`~torchfilt.pipeline.train_recipe` does); the message gives the first failure's
            own message. The other runs are kept; ``resume`` continues them.
    """
    import_ray()
    if not recipes:
        raise InputError("no recipes given")
    if resume and force:
        raise InputError("--resume continues the runs and --force discards them: pick one")
    stream = stream if stream is not None else sys.stderr
    rs = [r if isinstance(r, Recipe) else load_recipe(r) for r in recipes]
    units: list[tuple[str, Recipe]] = []
    if datasets:
        if len(rs) != 1:
            raise InputError("--dataset trains one recipe over several datasets: give one recipe")
        for d in datasets:
            p = Path(d).resolve()
            if not p.exists():
                raise InputError(f"--dataset {d}: not found")
            name = (p.parent if p.is_file() else p).name
            units.append((name, dataclasses.replace(rs[0], dataset=p)))
    else:
        units = [(r.name, r) for r in rs]
    seen: dict[str, int] = {}
    for i, (name, _) in enumerate(units):
        if name in seen:
            raise InputError(
                f"two units would share the run directory {Path(out) / name} "
                f"(units {seen[name] + 1} and {i + 1}); give them distinct names"
            )
        seen[name] = i
    results: dict[str, Path] = {}
    failures: list[str] = []
    with ray_session(address, workers=workers) as ray:
        output_dir(out)  # after Ray is reached: an unreachable cluster leaves nothing behind
        remote = ray.remote(_train_one).options(num_cpus=1, max_retries=max_retries)
        refs = {
            remote.remote(r, os.path.abspath(Path(out) / name), resume, force): name
            for name, r in units
        }
        left = list(refs)
        while left:
            ready, left = ray.wait(left, num_returns=1)
            name = refs[ready[0]]
            try:
                res = ray.get(ready[0])
            except Exception as e:
                failures.append(f"{name}: {_one_line(e)}")
                stream.write(f"train {name}: failed\n")
                continue
            results[name] = Path(res["bundle"])
            stream.write(f"train {name}: done in {res['seconds']:.1f} s -> {res['bundle']}\n")
            stream.flush()
    if failures:
        raise RunError(
            f"{len(failures)} of {len(units)} training runs failed (first: {failures[0]}); "
            "the finished runs are kept: pass --resume to continue the others"
        )
    return {name: results[name] for name, _ in units}
