"""The shared body of :meth:`GPTransition.fit <torchfilt.models.gp.GPTransition.fit>` and
:meth:`GPMeasurement.fit <torchfilt.models.gp.GPMeasurement.fit>`: build the model from its
training pairs, train its hyperparameters, freeze it.

Each ``fit`` states its options as explicit keyword arguments with their defaults (what
``help()`` and the API pages show) and forwards them to :func:`fit_model`, whose keyword-only
parameters are the one list of the options (:data:`FIT_KEYWORDS`; a test keeps the two fits'
signatures equal to it and their defaults equal to those of the methods they feed:
``GPModel._from_pairs``, :meth:`~torchfilt.models.gp.GPModel.optimize` and
:meth:`~torchfilt.models.gp.GPModel.freeze`). Not part of the public API.
"""

from __future__ import annotations

import inspect
from collections.abc import Callable, Mapping, Sequence
from typing import Any, Literal, TypeVar

import torch
from torch import Tensor

from torchfilt.models.gp.data import PairData
from torchfilt.models.gp.kernels import KernelName
from torchfilt.models.gp.model import GPModel
from torchfilt.models.gp.optimize import Callback
from torchfilt.models.gp.predictor import VarianceMode
from torchfilt.optim import OptimizerOptions

__all__ = [
    "FIT_KEYWORDS",
    "Inputs",
    "Noise",
    "NoiseFloor",
    "Structure",
    "fit_keywords",
    "fit_model",
]

#: The GP structures of ``structure=``.
Structure = Literal["independent", "multitask", "sparse"]
#: ``inputs=``: feature indices into ``[x, u]`` shared by all outputs, one list per output, or
#: ``None`` (all features).
Inputs = Sequence[int] | Sequence[Sequence[int]] | None
#: ``noise=``: a fixed noise variance (scalar or one per output), or ``None`` (learned).
Noise = float | Sequence[float] | Tensor | None
#: ``noise_floor=``: ``"auto"`` (from the data) or a variance (scalar or one per output).
NoiseFloor = Literal["auto"] | float | Sequence[float] | Tensor

_M = TypeVar("_M", bound=GPModel)


def fit_model(
    cls: type[_M],
    pairs: PairData,
    *,
    kernel: KernelName,
    structure: Structure,
    increment: bool = False,
    prior_mean: Callable[..., Tensor] | None,
    inputs: Inputs,
    noise: Noise,
    noise_floor: NoiseFloor,
    num_latents: int,
    task_rank: int,
    num_inducing: int,
    iterations: int | None,
    optimizer: OptimizerOptions | Literal["adam"] | None,
    natural_lr: float,
    subset: int | None,
    batch_size: int,
    variance: VarianceMode,
    rank: int | None,
    tol: float,
    chunk_size: int | None,
    device: str | torch.device | None,
    seed: int,
    callback: Callback | None,
    progress: bool,
    resume: dict[str, Any] | None,
) -> _M:
    """A ``cls`` built from ``pairs``, trained and frozen (the options are those of
    :meth:`GPTransition.fit <torchfilt.models.gp.GPTransition.fit>`; ``increment`` is a
    transition's only)."""
    model = cls._from_pairs(
        pairs, kernel=kernel, structure=structure, increment=increment, prior_mean=prior_mean,
        inputs=inputs, noise=noise, noise_floor=noise_floor, num_latents=num_latents,
        task_rank=task_rank, num_inducing=num_inducing, seed=seed,
    )  # fmt: skip
    if device is not None:
        model.to(device)
    model.optimize(
        iterations, optimizer=optimizer, natural_lr=natural_lr, subset=subset,
        batch_size=batch_size, seed=seed, callback=callback, progress=progress, resume=resume,
    )  # fmt: skip
    model.freeze(variance, rank, tol=tol, chunk_size=chunk_size)
    return model  # type: ignore[return-value]


#: The options of the GP fits: the keyword-only parameters of :func:`fit_model`.
FIT_KEYWORDS: tuple[str, ...] = tuple(
    p.name for p in inspect.signature(fit_model).parameters.values() if p.kind is p.KEYWORD_ONLY
)


def fit_keywords(scope: Mapping[str, Any]) -> dict[str, Any]:
    """The options a ``fit`` was called with, from its ``locals()`` (its arguments): the entries
    of :data:`FIT_KEYWORDS` it has."""
    return {k: scope[k] for k in FIT_KEYWORDS if k in scope}
