"""``GPTransition``: a GP transition model ``x_{k+1} = f(x_k, u_k) + w``."""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any, Literal

import torch
from torch import Tensor

from torchfilt.models.gp.data import transition_pairs
from torchfilt.models.gp.fitting import (
    Inputs,
    Noise,
    NoiseFloor,
    Structure,
    fit_keywords,
    fit_model,
)
from torchfilt.models.gp.kernels import KernelName
from torchfilt.models.gp.model import _ROLES, GPModel
from torchfilt.models.gp.optimize import Callback
from torchfilt.models.gp.predictor import VarianceMode
from torchfilt.optim import OptimizerOptions, deprecated_fit_keywords

__all__ = ["GPTransition"]


class GPTransition(GPModel):
    """A transition learned by GP regression: inputs ``(x_k, u_k)``, target ``x_{k+1}``.

    ``predict(x, u)`` returns the GP predictive mean of ``x_{k+1}`` and its variance (latent
    variance + likelihood noise) per point: a :class:`~torchfilt.CKF` turns the latter into ``Q``
    by the law of total variance over the cubature points.

    Example:
        >>> import torch, torchfilt
        >>> from torchfilt.models.gp import GPTransition
        >>> x = torch.randn(4, 31, 2, dtype=torch.float64).cumsum(-2) * 0.1  # 4 recordings
        >>> f = GPTransition.fit(x, increment=True, iterations=20, progress=False)
        >>> f.predict(torch.zeros(5, 2, dtype=torch.float64)).mean.shape
        torch.Size([5, 2])

    Raises:
        InputError: not one group per ``config`` group, or a ``prior_mean`` that does not match
            ``config.prior_mean`` (build one with ``fit`` or ``from_state``).
    """

    role = "transition"

    @classmethod
    @deprecated_fit_keywords("gp")
    def fit(
        cls,
        x: Tensor | Sequence[Tensor],
        u: Tensor | Sequence[Tensor] | None = None,
        x_next: Tensor | None = None,
        *,
        kernel: KernelName = "rbf",
        structure: Structure = "independent",
        increment: bool = False,
        prior_mean: Callable[..., Tensor] | None = None,
        inputs: Inputs = None,
        noise: Noise = None,
        noise_floor: NoiseFloor = "auto",
        num_latents: int = 1,
        task_rank: int = 1,
        num_inducing: int = 256,
        iterations: int | None = None,
        optimizer: OptimizerOptions | Literal["adam"] | None = None,
        natural_lr: float = 0.1,
        subset: int | None = 1000,
        batch_size: int = 1024,
        variance: VarianceMode = "auto",
        rank: int | None = None,
        tol: float = 0.05,
        chunk_size: int | None = None,
        dtype: torch.dtype = torch.float64,
        device: str | torch.device | None = None,
        seed: int = 0,
        callback: Callback | None = None,
        progress: bool = True,
        resume: dict[str, Any] | None = None,
    ) -> GPTransition:
        """Fit a GP transition and return it trained and frozen.

        Every option is a keyword argument; an unknown one (a misspelling) is an ``InputError``
        naming it and the valid ones. ``lr=`` of before still works for one release, with a
        ``DeprecationWarning``: it is ``optimizer=OptimizerOptions("adam", lr=...)``.

        Args:
            x: states ``x_k`` ``(..., N, n)`` together with ``x_next``; or, without ``x_next``,
                recordings: a tensor ``(..., T+1, n)`` (leading dimensions are separate
                recordings) or a list of ``(T_i+1, n)`` tensors. Pairs never cross recordings.
            u: inputs ``u_k`` aligned with ``x`` (``(..., N, nu)``; for recordings ``(..., T, nu)``
                or a list), or ``None``.
            x_next: successor states ``(..., N, n)``, or ``None`` for recordings.
            kernel: ``"rbf"`` (ARD), ``"matern52"``, ``"matern32"`` or ``"matern12"``.
            structure: ``"independent"`` (one GP per output, batched), ``"multitask"`` (LMC,
                correlated outputs, exact; small logs) or ``"sparse"`` (SVGP, minibatches).
            increment: learn ``x_{k+1} - x_k``.
            prior_mean: nominal model ``fn(x, u) -> x_{k+1}`` (torch, broadcasting); the GP learns
                the residual. Exclusive with ``increment``.
            inputs: input selection: feature indices into ``[x, u]`` shared by all outputs, or one
                list per output (``None``: all).
            noise: fix the noise variance: a scalar or one per output, ``(n,)``, in state units
                squared (``None``: learned).
            noise_floor: ``"auto"`` (from the data: see :mod:`~torchfilt.models.gp.noise`) or a
                variance: a scalar or one per output, ``(n,)``.
            num_latents: LMC latent processes (``structure="multitask"``).
            task_rank: LMC task rank (``structure="multitask"``).
            num_inducing: inducing points per output (``structure="sparse"``).
            iterations: Adam iterations (``None``: 200, ``DEFAULTS["gp"]``).
            optimizer: :class:`~torchfilt.optim.OptimizerOptions` of the Adam steps (``None``:
                ``lr`` 0.05; at most 1), or ``"adam"``.
            natural_lr: natural-gradient step for a sparse model's ``q(u)``.
            subset: train the hyperparameters of an exact model on at most this many random rows
                (``None``: all), then condition on all rows.
            batch_size: minibatch of a sparse model.
            variance: frozen variance form, ``"auto"``, ``"exact"`` or ``"lowrank"``
                (:meth:`~torchfilt.models.gp.GPModel.freeze`).
            rank: the low-rank root's rank (``variance="lowrank"``).
            tol: relative variance tolerance of ``variance="auto"``.
            chunk_size: points per kernel chunk (``None``: from the training set's size; see
                :meth:`~torchfilt.models.gp.GPModel.freeze`).
            dtype: training dtype.
            device: train and keep the model on this device (e.g. ``"cuda"``; ``None``: the CPU,
                where the data are prepared).
            seed: seeds every random choice.
            callback: per-iteration ``fn(FitState) -> bool | None``; ``True`` stops.
            progress: progress line on stderr.
            resume: checkpoint from ``FitState.checkpoint()`` to continue.

        Returns:
            The trained, frozen model.

        Raises:
            InputError: an unknown keyword argument, or an invalid option value.
        """
        options = fit_keywords(locals())
        pairs = transition_pairs(x, u, x_next, dtype=dtype)
        return fit_model(cls, pairs, **options)


_ROLES["transition"] = GPTransition
