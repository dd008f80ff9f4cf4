"""``GPMeasurement``: a GP measurement model ``y_k = h(x_k, u_k) + v``."""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any, Literal

import torch
from torch import Tensor

from torchfilt.models.gp.data import measurement_pairs
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

__all__ = ["GPMeasurement"]


class GPMeasurement(GPModel):
    """A measurement model learned by GP regression: input ``x_k`` (and ``u_k``), target ``y_k``.

    ``predict(x, u)`` returns the predictive mean of ``y_k`` and its variance (latent variance +
    likelihood noise) per point; a :class:`~torchfilt.CKF` adds the cubature average of the latter
    to ``P_yy`` (the learned ``R``).

    Example:
        >>> import torch
        >>> from torchfilt.models.gp import GPMeasurement
        >>> x = torch.linspace(0, 3, 60, dtype=torch.float64).reshape(-1, 1).repeat(1, 2)
        >>> y = torch.sin(x[:, :1]) + 0.01 * torch.randn(60, 1, dtype=torch.float64)
        >>> h = GPMeasurement.fit(x, y, inputs=[0], iterations=30, progress=False)
        >>> h.predict(x[:3]).var.shape
        torch.Size([3, 1])

    Raises:
        InputError: not one group per ``config`` group, or a ``prior_mean`` that does not match
            ``config.prior_mean`` (build one with ``fit`` or ``from_state``).
    """

    role = "measurement"

    @classmethod
    @deprecated_fit_keywords("gp")
    def fit(
        cls,
        x: Tensor | Sequence[Tensor],
        y: Tensor | Sequence[Tensor],
        u: Tensor | Sequence[Tensor] | None = None,
        *,
        kernel: KernelName = "rbf",
        structure: Structure = "independent",
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
    ) -> GPMeasurement:
        """Fit a GP measurement model and return it trained and frozen.

        The options are those of :meth:`GPTransition.fit <torchfilt.models.gp.GPTransition.fit>`
        but ``increment``; an unknown keyword is an ``InputError``, and ``lr=`` of before still
        works for one release, with a ``DeprecationWarning``. Input selection matters most here:
        a sensor that depends on some states only should see only those (``inputs=[0]``), or the
        GP extrapolates along the others.

        Args:
            x: states ``(..., N, n)`` or a list of ``(T_i, n)`` recordings.
            y: measurements ``(..., N, m)`` or a list of ``(T_i, m)``; NaN entries are missing
                and are dropped per output.
            u: inputs ``(..., N, nu)``, a list, or ``None`` (the usual case: ``h`` of ``x`` only).
            kernel: ``"rbf"`` (ARD), ``"matern52"``, ``"matern32"`` or ``"matern12"``.
            structure: ``"independent"`` (one GP per output, batched), ``"multitask"`` (LMC,
                correlated outputs, exact) or ``"sparse"`` (SVGP, minibatches).
            prior_mean: nominal sensor ``h0(x, u) -> y`` (torch, broadcasting); the GP learns the
                residual.
            inputs: input selection: feature indices into ``[x, u]`` shared by all outputs, or one
                list per output (``None``: all).
            noise: fix the noise variance: a scalar or one per output, ``(m,)``, in measurement
                units squared (``None``: learned).
            noise_floor: ``"auto"`` (from the data: see :mod:`~torchfilt.models.gp.noise`) or a
                variance: a scalar or one per output, ``(m,)``.
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
        pairs = measurement_pairs(x, y, u, dtype=dtype)
        return fit_model(cls, pairs, **options)


_ROLES["measurement"] = GPMeasurement
