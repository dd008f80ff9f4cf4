"""``GPTransition``: a GP transition model ``x_{k+1} = f(x_k, u_k) + w``."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import torch
from torch import Tensor

from torchfilt.models.gp.data import transition_pairs
from torchfilt.models.gp.model import _ROLES, GPModel

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
    def fit(
        cls,
        x: Tensor | Sequence[Tensor],
        u: Tensor | Sequence[Tensor] | None = None,
        x_next: Tensor | None = None,
        **options: Any,
    ) -> GPTransition:
        """Fit a GP transition and return it trained and frozen.

        Args:
            x: states ``x_k`` ``(..., N, n)`` together with ``x_next``; or, without ``x_next``,
                recordings: a tensor ``(..., T+1, n)`` (leading dimensions are separate
                recordings) or a list of ``(T_i+1, n)`` tensors. Pairs never cross recordings.
            u: inputs ``u_k`` aligned with ``x`` (``(..., N, nu)``; for recordings ``(..., T, nu)``
                or a list), or ``None``.
            x_next: successor states ``(..., N, n)``, or ``None`` for recordings.
            **options: see below.

        Keyword Args:
            kernel (str): ``"rbf"`` (default, ARD), ``"matern52"``, ``"matern32"``,
                ``"matern12"``.
            structure (str): ``"independent"`` (default; one GP per output, batched),
                ``"multitask"`` (LMC, correlated outputs, exact; small logs) or ``"sparse"``
                (SVGP, minibatches).
            increment (bool): learn ``x_{k+1} - x_k`` (default ``False``).
            prior_mean (Callable | None): nominal model ``fn(x, u) -> x_{k+1}`` (torch,
                broadcasting); the GP learns the residual. Exclusive with ``increment``.
            inputs (Sequence[int] | Sequence[Sequence[int]] | None): input selection: feature
                indices into ``[x, u]`` shared by all outputs, or one list per output (default:
                all).
            noise (float | Sequence[float] | Tensor | None): fix the noise variance (scalar or
                one per output, in state units squared).
            noise_floor (str | float | Sequence[float] | Tensor): ``"auto"`` (default, from the
                data: see :mod:`~torchfilt.models.gp.noise`) or a variance (scalar or per output).
            num_latents (int): LMC latent processes (``structure="multitask"``, default 1).
            task_rank (int): LMC task rank (``structure="multitask"``, default 1).
            num_inducing (int): inducing points per output (``structure="sparse"``, default 256).
            iterations (int): Adam iterations (default 200).
            lr (float): learning rate (default 0.05).
            natural_lr (float): natural-gradient step for a sparse model's ``q(u)`` (default 0.1).
            subset (int | None): train hyperparameters of an exact model on at most this many
                random rows (default 1000; ``None`` for all), then condition on all rows.
            batch_size (int): minibatch of a sparse model (default 1024).
            variance (str): frozen variance form, ``"auto"`` (default), ``"exact"`` or
                ``"lowrank"``. See ``GPModel.freeze``.
            rank (int | None): the low-rank root's rank (``GPModel.freeze``).
            tol (float): tolerance of ``variance="auto"`` (default 0.05).
            chunk_size (int): points per kernel chunk (default 128).
            dtype (torch.dtype): training dtype (default ``torch.float64``).
            device (str | torch.device | None): train and keep the model on this device (e.g.
                ``"cuda"``; default: the CPU, where the data are prepared).
            seed (int): seeds every random choice (default 0).
            callback (Callable | None): per-iteration ``fn(FitState) -> bool | None``; ``True``
                stops.
            progress (bool): progress line on stderr (default ``True``).
            resume (dict | None): checkpoint from ``FitState.checkpoint()`` to continue.

        Returns:
            The trained, frozen model.

        Raises:
            InputError: an unknown keyword argument, or an invalid option value.
        """
        dtype = options.pop("dtype", torch.float64)
        pairs = transition_pairs(x, u, x_next, dtype=dtype)
        return cls._fit(pairs, options)  # type: ignore[return-value]


_ROLES["transition"] = GPTransition
