"""Training recipes: TOML files in ``trainers/`` that say what to train on and how.

A recipe names the dataset, the model of each side (a GP with its options, or a built-in analytic
model), the optimiser and iterations, checkpointing, and the seed::

    name = "reentry"
    seed = 0

    [dataset]
    path = "../data/reentry"           # relative to the recipe file

    [transition]                       # GPTransition.fit options
    increment = true
    inputs = ["altitude", "velocity", "ballistic"]
    iterations = 150

    [measurement]                      # GPMeasurement.fit options
    inputs = ["altitude"]              # input selection by channel name
    iterations = 150

    [train]
    checkpoint_every = 25

A side may instead be a built-in model: ``[measurement] model = "system:reentry"``. A GP's
``prior_mean`` is a built-in nominal model: ``prior_mean = {system = "reentry", gamma = 4e-5}``.
Unknown keys are errors (a typo must not silently train a different model).
"""

from __future__ import annotations

import copy
import hashlib
import json
import tomllib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from torchfilt.exceptions import RecipeError

__all__ = ["CALIBRATE_DEFAULTS", "GP_OPTIONS", "Recipe", "RecipeError", "load_recipe"]

#: Options passed through to ``GPTransition.fit`` / ``GPMeasurement.fit``.
GP_OPTIONS = frozenset(
    {
        "kernel",
        "structure",
        "increment",
        "prior_mean",
        "inputs",
        "noise",
        "noise_floor",
        "num_latents",
        "task_rank",
        "num_inducing",
        "iterations",
        "lr",
        "natural_lr",
        "subset",
        "batch_size",
        "variance",
        "rank",
        "tol",
        "chunk_size",
    }
)
_TOP = {
    "name",
    "description",
    "seed",
    "dataset",
    "transition",
    "measurement",
    "train",
    "filter",
    "calibrate",
}
_DATASET = {"path"}
_TRAIN = {"checkpoint_every", "dtype", "threads"}
_FILTER = {"prior", "mean", "cov_diag"}
#: ``[calibrate]``: the calibration stage (see :func:`torchfilt.training.calibrate`), with defaults.
CALIBRATE_DEFAULTS: dict[str, Any] = {
    "enabled": True,
    "sides": "learned",
    "window": 100,
    "burn_in": 20,
    "iterations": 100,
    "lr": 0.1,
    "optimizer": "adam",
    "patience": 15,
    "inflate_only": True,
}


@dataclass
class Recipe:
    """A parsed, validated recipe.

    Attributes:
        path: the recipe file (``None`` if built in code).
        name: run name.
        seed: random seed for every random choice.
        dataset: path of the dataset (manifest or folder), resolved.
        transition: GP options, or ``{"model": "system:NAME"}``.
        measurement: GP options, or ``{"model": "system:NAME"}``.
        checkpoint_every: iterations between checkpoints.
        dtype: training dtype name (``"float64"`` or ``"float32"``).
        threads: torch threads for training (``None``: leave as is).
        filter: default filter prior for the bundle (``prior = "data"`` (default), ``"system:NAME"``,
            or explicit ``mean`` and ``cov_diag``).
        calibrate: the calibration stage (``[calibrate]``, on by default; ``enabled = false``
            turns it off): ``sides`` (``"learned"``, the GP sides, or a list of
            ``"transition"``/``"measurement"``), ``window``, ``burn_in``, ``iterations``, ``lr``,
            ``optimizer`` (``"adam"`` or ``"lbfgs"``), ``patience`` (early stopping on the
            validation recordings), ``inflate_only`` (scales >= 1, default ``true``).
        description: free text.
    """

    path: Path | None
    name: str
    seed: int
    dataset: Path
    transition: dict[str, Any]
    measurement: dict[str, Any]
    checkpoint_every: int = 25
    dtype: str = "float64"
    threads: int | None = None
    filter: dict[str, Any] = field(default_factory=dict)
    description: str = ""
    calibrate: dict[str, Any] = field(default_factory=lambda: dict(CALIBRATE_DEFAULTS))

    def resolved(self) -> dict[str, Any]:
        """The fully resolved configuration (what a run directory records)."""
        return {
            "name": self.name,
            "description": self.description,
            "seed": self.seed,
            "dataset": str(self.dataset),
            "transition": copy.deepcopy(self.transition),
            "measurement": copy.deepcopy(self.measurement),
            "train": {
                "checkpoint_every": self.checkpoint_every,
                "dtype": self.dtype,
                "threads": self.threads,
            },
            "filter": copy.deepcopy(self.filter),
            "calibrate": copy.deepcopy(self.calibrate),
        }

    def digest(self) -> str:
        """SHA-256 of the resolved configuration (identifies the recipe in a run directory)."""
        return hashlib.sha256(json.dumps(self.resolved(), sort_keys=True).encode()).hexdigest()


def _check_keys(
    table: Any, allowed: set[str] | frozenset[str], where: str, path: Path | None
) -> dict[str, Any]:
    if not isinstance(table, dict):
        raise RecipeError(f"{path}: [{where}] must be a table")
    unknown = sorted(set(table) - set(allowed))
    if unknown:
        raise RecipeError(
            f"{path}: unknown key(s) {unknown} in [{where}]; allowed: {sorted(allowed)}"
        )
    return dict(table)


def _side(table: Any, where: str, path: Path | None) -> dict[str, Any]:
    if table is None:
        raise RecipeError(f'{path}: missing [{where}] table (GP options, or model = "system:NAME")')
    if isinstance(table, dict) and "model" in table:
        t = _check_keys(table, {"model"}, where, path)
        if not str(t["model"]).startswith("system:"):
            raise RecipeError(f'{path}: [{where}] model must be "system:NAME", got {t["model"]!r}')
        return t
    t = _check_keys(table, GP_OPTIONS, where, path)
    pm = t.get("prior_mean")
    if pm is not None and (not isinstance(pm, dict) or "system" not in pm):
        raise RecipeError(
            f"{path}: [{where}] prior_mean must be a table with 'system' (and parameters)"
        )
    return t


def load_recipe(path: str | Path) -> Recipe:
    """Read and validate a recipe TOML file."""
    path = Path(path)
    if not path.is_file():
        raise RecipeError(f"{path}: recipe not found")
    try:
        d = tomllib.loads(path.read_text(encoding="utf-8"))
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as e:
        raise RecipeError(f"{path}: not valid TOML ({e})") from None
    d = _check_keys(d, _TOP, "top level", path)
    ds = _check_keys(d.get("dataset", {}), _DATASET, "dataset", path)
    if "path" not in ds:
        raise RecipeError(f"{path}: [dataset] needs 'path'")
    train = _check_keys(d.get("train", {}), _TRAIN, "train", path)
    filt = _check_keys(d.get("filter", {}), _FILTER, "filter", path)
    dtype = str(train.get("dtype", "float64"))
    if dtype not in ("float64", "float32"):
        raise RecipeError(f"{path}: [train] dtype must be 'float64' or 'float32', got {dtype!r}")
    every = int(train.get("checkpoint_every", 25))
    if every < 1:
        raise RecipeError(f"{path}: [train] checkpoint_every must be >= 1, got {every}")
    calib = _calibrate(d.get("calibrate", {}), path)
    seed = d.get("seed", 0)
    if not isinstance(seed, int):
        raise RecipeError(f"{path}: seed must be an integer, got {seed!r}")
    return Recipe(
        path=path,
        name=str(d.get("name", path.stem)),
        seed=seed,
        dataset=(path.parent / str(ds["path"])).resolve(),
        transition=_side(d.get("transition"), "transition", path),
        measurement=_side(d.get("measurement"), "measurement", path),
        checkpoint_every=every,
        dtype=dtype,
        threads=None if train.get("threads") is None else int(train["threads"]),
        filter=filt,
        description=str(d.get("description", "")),
        calibrate=calib,
    )


def _calibrate(table: Any, path: Path | None) -> dict[str, Any]:
    """Validate ``[calibrate]`` and fill in its defaults."""
    t = _check_keys(table, set(CALIBRATE_DEFAULTS), "calibrate", path)
    out = {**CALIBRATE_DEFAULTS, **t}
    for key in ("enabled", "inflate_only"):
        if not isinstance(out[key], bool):
            raise RecipeError(f"{path}: [calibrate] {key} must be true or false")
    sides = out["sides"]
    ok_sides = sides == "learned" or (
        isinstance(sides, list) and sides and set(sides) <= {"transition", "measurement"}
    )
    if not ok_sides:
        raise RecipeError(
            f'{path}: [calibrate] sides must be "learned" or a list of "transition" and/or '
            f'"measurement", got {sides!r}'
        )
    for key in ("window", "iterations", "patience"):
        v = out[key]
        if not isinstance(v, int) or isinstance(v, bool) or v < 1:
            raise RecipeError(f"{path}: [calibrate] {key} must be a positive integer, got {v!r}")
    b = out["burn_in"]
    if not isinstance(b, int) or isinstance(b, bool) or not 0 <= b < out["window"]:
        raise RecipeError(
            f"{path}: [calibrate] burn_in must be an integer in [0, window), got {b!r}"
        )
    lr = out["lr"]
    if not isinstance(lr, int | float) or isinstance(lr, bool) or not 0 < float(lr) <= 10:
        raise RecipeError(f"{path}: [calibrate] lr must be a number in (0, 10], got {lr!r}")
    out["lr"] = float(lr)
    if out["optimizer"] not in ("adam", "lbfgs"):
        raise RecipeError(
            f'{path}: [calibrate] optimizer must be "adam" or "lbfgs", got {out["optimizer"]!r}'
        )
    return out
