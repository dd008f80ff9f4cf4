"""The training loop: Adam on the negative log marginal likelihood (exact) or ELBO (sparse; plus
natural-gradient steps for the variational distribution).

Progress goes to stderr as a light line every tenth of the run (``progress=False`` silences it). A
per-iteration callback receives a :class:`FitState` from which a checkpoint (model state +
optimizer state + iteration, plain tensors and dicts) can be taken; ``fit(..., resume=checkpoint)``
continues from it.
"""

from __future__ import annotations

import copy
import math
import sys
import time
from collections.abc import Callable, Iterable, Sequence
from typing import Any, NamedTuple, TextIO

import gpytorch
import torch
from torch import Tensor, nn

from torchfilt.exceptions import ModelError

__all__ = ["FitDivergedError", "FitState", "Progress", "run_adam"]


class FitDivergedError(ModelError, FloatingPointError):
    """The training loss became non-finite (too large a learning rate, too low a noise floor,
    outliers). A :class:`~torchfilt.exceptions.ModelError`, and a ``FloatingPointError`` as
    before."""


class FitState(NamedTuple):
    """What a training callback sees after each iteration.

    Attributes:
        iteration: iterations completed (counting those of a resumed run).
        iterations: total iterations planned.
        loss: the objective at this iteration (negative log marginal likelihood or ELBO per
            training point, summed over outputs).
        elapsed: seconds since this call to ``fit`` started.
        model: the model being trained (a :class:`~torchfilt.models.gp.GPModel`).
        optimizer: the ``torch.optim.Adam`` instance (hyperparameters).
        natural: the natural-gradient optimizers of sparse groups' ``q(u)`` (may be empty).
    """

    iteration: int
    iterations: int
    loss: float
    elapsed: float
    model: Any
    optimizer: torch.optim.Optimizer | None
    natural: tuple[torch.optim.Optimizer, ...] = ()

    def hyperparameters(self) -> dict[str, Tensor]:
        """The model's current hyperparameters in target/input units (see ``GPModel.hyperparameters``)."""
        return dict(self.model.hyperparameters())

    def checkpoint(self) -> dict[str, Any]:
        """Model state, optimizer state and iteration: plain tensors and dicts, for
        ``torch.save`` and ``torch.load(weights_only=True)``; pass it to ``fit(..., resume=...)``."""
        # state_dict() returns live references; the optimizers keep updating them in place.
        return {
            "model": self.model.to_state(),
            "optimizer": {
                "adam": None
                if self.optimizer is None
                else copy.deepcopy(self.optimizer.state_dict()),
                "natural": [copy.deepcopy(o.state_dict()) for o in self.natural],
            },
            "iteration": self.iteration,
        }


#: A callback; returning ``True`` stops training after this iteration.
Callback = Callable[[FitState], bool | None]


class Progress:
    """A light progress line on a text stream: every tenth of the run and at the end.

    Args:
        label: prefix (the model's class name).
        total: planned iterations.
        stream: where to write (default ``sys.stderr``).
    """

    def __init__(self, label: str, total: int, stream: TextIO | None = None) -> None:
        self.label = label
        self.total = total
        self.every = max(1, total // 10)
        self.stream = stream if stream is not None else sys.stderr

    def __call__(self, it: int, loss: float, elapsed: float, final: bool = False) -> None:
        if final or it % self.every == 0 or it == self.total:
            self.stream.write(
                f"{self.label}: iteration {it}/{self.total}  loss {loss:.5g}  ({elapsed:.1f} s)\n"
            )
            self.stream.flush()


def run_adam(
    params: Iterable[nn.Parameter],
    loss_fn: Callable[[int], Tensor],
    *,
    natural: Sequence[tuple[Sequence[nn.Parameter], int]] = (),
    natural_lr: float = 0.1,
    iterations: int,
    lr: float,
    start: int = 0,
    optimizer_state: dict[str, Any] | None = None,
    callback: Callback | None = None,
    progress: Progress | None = None,
    model: Any = None,
) -> list[float]:
    """Minimise ``loss_fn(iteration)`` with Adam from iteration ``start`` to ``iterations``.

    Args:
        params: parameters to optimise with Adam.
        loss_fn: the objective at an iteration (the iteration picks a minibatch).
        natural: ``(parameters, num_data)`` of each sparse group's natural variational
            parameters, stepped with GPyTorch's ``NGD`` (one optimizer per group).
        natural_lr: natural-gradient step size.
        iterations: total planned iterations (``start`` of them already done).
        lr: learning rate.
        start: iterations already done (resume).
        optimizer_state: the ``"optimizer"`` entry of a checkpoint, to resume from.
        callback: called after each iteration with a :class:`FitState`; ``True`` stops.
        progress: progress printer, or ``None`` for silence.
        model: passed to the callback.

    Returns:
        The loss of each iteration run.

    Raises:
        FitDivergedError: if the loss becomes non-finite.
    """
    plist = [p for p in params if p.requires_grad]
    opt = torch.optim.Adam(plist, lr=lr) if plist else None
    ngd = tuple(gpytorch.optim.NGD(list(ps), num_data=n, lr=natural_lr) for ps, n in natural)
    if opt is None and not ngd:  # nothing to learn (e.g. every output constant)
        return []
    if optimizer_state is not None:
        if opt is not None and optimizer_state.get("adam") is not None:
            opt.load_state_dict(optimizer_state["adam"])
        for o, st in zip(ngd, optimizer_state.get("natural", []), strict=False):
            o.load_state_dict(st)
    everything = ([opt] if opt is not None else []) + list(ngd)
    t0 = time.perf_counter()
    losses: list[float] = []
    for it in range(start + 1, iterations + 1):
        for o in everything:
            o.zero_grad(set_to_none=True)
        loss = loss_fn(it)
        value = float(loss.detach())
        if not math.isfinite(value):
            raise FitDivergedError(
                f"training loss became {value} at iteration {it}; lower lr, raise the noise floor, "
                "or check the data for outliers"
            )
        loss.backward()
        for o in everything:
            o.step()
        losses.append(value)
        elapsed = time.perf_counter() - t0
        if progress is not None:
            progress(it, value, elapsed)
        state = FitState(it, iterations, value, elapsed, model, opt, ngd)
        if callback is not None and callback(state):
            if progress is not None:
                progress(it, value, elapsed, final=True)
            break
    return losses
