"""A recipe checked against its dataset before anything of a run is written: the channels a side
selects, the ``[filter]`` prior (the bundle's default), the ``states = "none"`` options."""

from __future__ import annotations

from typing import Any

import torch
from torch import Tensor

from torchfilt.exceptions import DataError, InputError, RecipeError
from torchfilt.io import Dataset
from torchfilt.io.recording import Recording
from torchfilt.pipeline.bundle import nominal_model
from torchfilt.pipeline.entry_point import is_entry_point, load_entry_point
from torchfilt.pipeline.recipe import Recipe
from torchfilt.systems import get_system

__all__ = ["STAGES"]

STAGES = ("transition", "measurement")


def _feature_indices(names: list[Any] | None, features: list[str], where: str) -> list[Any] | None:
    """Translate input selection by channel name into feature indices."""
    if names is None:
        return None

    def one(v: Any) -> int:
        if isinstance(v, int):
            if not 0 <= v < len(features):
                raise RecipeError(
                    f"[{where}] inputs: index {v} out of range for features {features}"
                )
            return v
        if not isinstance(v, str) or v not in features:
            raise RecipeError(
                f"[{where}] inputs: unknown channel {v!r}; the channels are {features}"
            )
        return features.index(v)

    if names and isinstance(names[0], list):
        return [[one(v) for v in per] for per in names]
    return [one(v) for v in names]


def _prior(recipe: Recipe, train: list[Recording], n: int) -> tuple[Tensor, Tensor, str]:
    """The bundle's default filter prior: from the data's initial states, a system, or explicit."""
    f = recipe.filter
    if "mean" in f or "cov_diag" in f:
        if "mean" not in f or "cov_diag" not in f:
            raise RecipeError("[filter] give both mean and cov_diag")
        try:
            m = torch.tensor(f["mean"], dtype=torch.float64)
            c = torch.diag(torch.tensor(f["cov_diag"], dtype=torch.float64))
        except (TypeError, ValueError, RuntimeError):
            raise RecipeError("[filter] mean and cov_diag must be lists of numbers") from None
        if m.shape != (n,) or c.shape != (n, n):
            raise RecipeError(f"[filter] mean and cov_diag must have {n} entries (the states)")
        if not bool(torch.isfinite(m).all()) or not bool((c.diagonal() > 0).all()):
            raise RecipeError("[filter] mean must be finite and cov_diag positive")
        return m, c, "recipe"
    prior = str(f.get("prior", "data"))
    if prior.startswith("system:"):
        s = get_system(prior.split(":", 1)[1])
        return s.prior_mean(), s.prior_cov(), prior
    if prior != "data":
        raise RecipeError(
            f"[filter] prior must be 'data', 'system:NAME' or mean/cov_diag, got {prior!r}"
        )
    x0 = torch.stack([r.states[0].to(torch.float64) for r in train])
    m = x0.mean(0)
    if x0.shape[0] > n:
        c = torch.cov(x0.T).reshape(n, n)
    else:
        allx = torch.cat([r.states.to(torch.float64) for r in train])
        c = torch.diag(allx.var(0))
    c = 0.5 * (c + c.T) + torch.diag(c.diagonal().abs() * 1e-9 + torch.finfo(torch.float64).tiny)
    return m, c, "data: mean and covariance of the training recordings' initial states"


def _check_against_dataset(r: Recipe, ds: Dataset) -> tuple[Tensor, Tensor, str]:
    """Check the recipe against the dataset before any training: training recordings exist, the
    ``inputs`` of each GP side name channels, a ``prior_mean`` system exists, the ``[filter]``
    prior fits. Returns the bundle's default filter prior. Errors name the recipe file."""
    try:
        return _check_channels(r, ds)
    except RecipeError as e:
        if r.path is None:
            raise
        raise RecipeError(f"{r.path}: {e}") from None


def _check_channels(r: Recipe, ds: Dataset) -> tuple[Tensor, Tensor, str]:
    train = ds.split("train")
    if not train:
        raise DataError("the dataset has no training recordings", path=ds.manifest_path)
    states, inputs = ds.manifest.names("state"), ds.manifest.names("input")
    if r.states == "none":
        _check_measurement_only(r, ds)
        return _prior(r, train, len(states))
    for stage in STAGES:
        opts = getattr(r, stage)
        if "model" in opts:
            _known_side(r, ds, stage)
            continue
        features = states + inputs if stage == "transition" else states
        if "inputs" in opts:
            sel = opts["inputs"]
            if not isinstance(sel, list):
                raise RecipeError(f"[{stage}] inputs must be a list of channel names")
            _feature_indices(sel, features, stage)
        if opts.get("prior_mean") is not None:
            nominal_model(opts["prior_mean"])
    return _prior(r, train, len(states))


def _known_side(r: Recipe, ds: Dataset, stage: str) -> None:
    """A side's known ``model``: the built-in system exists, or the entry point imports and maps
    the dataset's states to its measurement channels (see :mod:`torchfilt.pipeline.entry_point`)."""
    opts = getattr(r, stage)
    spec = str(opts["model"])
    if stage == "measurement" and is_entry_point(spec):
        load_entry_point(
            spec, opts.get("R"), role=stage, state_dim=ds.state_dim, obs_dim=ds.obs_dim,
            input_dim=ds.input_dim,
        )  # fmt: skip
        return
    get_system(spec.split(":", 1)[1])


def _known_channels(r: Recipe, ds: Dataset) -> list[int]:
    """``[measurement_only] known_channels`` as measurement indices (default: all)."""
    names = ds.manifest.names("measurement")
    kc = r.measurement_only.get("known_channels")
    if kc is None:
        return list(range(len(names)))
    unknown = [c for c in kc if c not in names]
    if unknown:
        raise RecipeError(
            f"[measurement_only] known_channels: unknown measurement channel(s) {unknown}; the "
            f"measurement channels are {names}"
        )
    return [names.index(c) for c in kc]


def _check_measurement_only(r: Recipe, ds: Dataset) -> None:
    """``states = "none"`` against the dataset: the measurement system fits its channels, the
    known channels exist, the nominal model maps the states, ``process_noise`` has one value per
    state."""
    n, m = ds.state_dim, ds.obs_dim
    if is_entry_point(r.measurement["model"]):
        _known_side(r, ds, "measurement")
        _check_nominal(r, ds)
        return
    name = str(r.measurement["model"]).split(":", 1)[1]
    try:
        spec = get_system(name)
    except InputError as e:
        raise RecipeError(f"[measurement] model: {e}") from None
    if len(spec.states) != n or len(spec.measurements) != m:
        raise RecipeError(
            f'[measurement] model = "system:{name}" maps {len(spec.states)} states to '
            f"{len(spec.measurements)} measurements, but the dataset declares {n} state and {m} "
            "measurement channels"
        )
    _check_nominal(r, ds)


def _check_nominal(r: Recipe, ds: Dataset) -> None:
    """The known channels exist, the nominal model maps the states, ``process_noise`` has one
    value per state."""
    n, nu = ds.state_dim, ds.input_dim
    _known_channels(r, ds)
    o = r.measurement_only
    if o["nominal"] is not None:
        try:
            g = nominal_model(o["nominal"])
        except (InputError, TypeError, ValueError) as e:
            raise RecipeError(f"[measurement_only] nominal: {e}") from None
        u = torch.zeros(1, nu, dtype=torch.float64) if nu else None
        try:
            out = g(torch.zeros(1, n, dtype=torch.float64), u)
        except Exception as e:
            raise RecipeError(
                f"[measurement_only] nominal {o['nominal']!r} does not map the dataset's {n} "
                f"states ({type(e).__name__}: {e})"
            ) from None
        if tuple(out.shape) != (1, n):
            raise RecipeError(
                f"[measurement_only] nominal {o['nominal']!r} maps {n} states to shape "
                f"{tuple(out.shape)[1:]}, expected ({n},)"
            )
    pn = o["process_noise"]
    if isinstance(pn, list) and len(pn) not in (1, n):
        raise RecipeError(
            f"[measurement_only] process_noise: {len(pn)} values for {n} states {ds.manifest.names('state')}"
        )
