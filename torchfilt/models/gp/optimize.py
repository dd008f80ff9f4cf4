"""The training of a GP's hyperparameters: Adam on the negative log marginal likelihood (exact)
or ELBO (sparse; plus natural-gradient steps for the variational distribution), one step per
iteration of the fitting loop every fit shares (:class:`torchfilt.optim.FitLoop`).

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
from collections.abc import Callable, Collection, Iterable, Sequence
from dataclasses import replace
from typing import Any, NamedTuple, TextIO

import gpytorch
import torch
from torch import Tensor, nn

from torchfilt.exceptions import InputError, ModelError
from torchfilt.models.gp.group import GPGroup
from torchfilt.optim import DEFAULTS, FitLoop, Outcome, free_parameters, make_optimizer

__all__ = ["FitDivergedError", "FitState", "Progress", "run_adam", "train_groups"]


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
        """The model's current hyperparameters in target/input units (see
        ``GPModel.hyperparameters``): ``noise`` ``(d,)``, ``noise_floor`` ``(d,)`` and the kernel
        hyperparameters."""
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
        self.start = time.perf_counter()

    def __call__(self, it: int, loss: float, elapsed: float, final: bool = False) -> None:
        if final or it % self.every == 0 or it == self.total:
            self._write(it, f"loss {loss:.5g}", elapsed)

    def update(self, done: int, info: str = "", final: bool = False) -> None:
        """Show iteration ``done`` with ``info`` (the loop's :class:`~torchfilt.optim.Reporter`
        protocol), every tenth of the run, at the end, and when ``final``."""
        if final or done % self.every == 0 or done == self.total:
            self._write(done, info, time.perf_counter() - self.start)

    def _write(self, it: int, info: str, elapsed: float) -> None:
        self.stream.write(f"{self.label}: iteration {it}/{self.total}  {info}  ({elapsed:.1f} s)\n")
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
    # the options pick the optimiser; the budget is the loop's (a GP may train 0 iterations)
    options = replace(DEFAULTS["gp"].optimizer, lr=lr)
    opt = make_optimizer(plist, options) if plist else None
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

    def step(it: int) -> Outcome:
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
        state = FitState(it, iterations, value, time.perf_counter() - t0, model, opt, ngd)
        return Outcome({"iteration": it, "loss": value}, state, f"loss {value:.5g}")

    stop = DEFAULTS["gp"].stopping  # the windowed convergence rule, on by default
    loop = FitLoop(
        iterations=iterations,
        progress=progress,
        callback=callback,
        rtol=stop.rtol,
        rtol_window=stop.rtol_window,
        start=start,
    )
    if loop.run(step) == "callback" and progress is not None:
        progress.update(loop.iteration, f"loss {losses[-1]:.5g}", final=True)
    return losses


def train_groups(
    model: Any,
    *,
    iterations: int,
    lr: float,
    natural_lr: float,
    subset: int | None,
    batch_size: int,
    seed: int,
    callback: Callback | None,
    progress: bool,
    start: int = 0,
    optimizer_state: dict[str, Any] | None = None,
    fixed: Collection[str] = (),
) -> list[float]:
    """Train the hyperparameters of ``model``'s groups (a :class:`~torchfilt.models.gp.GPModel`;
    see :meth:`~torchfilt.models.gp.GPModel.optimize` for the arguments): an exact group on a
    seeded subset of its rows, a sparse one on seeded minibatches with natural-gradient steps for
    its ``q(u)``.

    Returns:
        The loss of each iteration run.
    """
    groups = [grp for grp in model.groups if isinstance(grp, GPGroup)]
    gen = torch.Generator().manual_seed(seed)
    for grp in groups:
        if subset is not None and grp.structure != "sparse" and grp.num_points > subset:
            grp.use_rows(
                torch.randperm(grp.num_points, generator=gen)[:subset].to(grp.train_x.device)
            )

    def loss_fn(it: int) -> Tensor:
        g = torch.Generator().manual_seed(seed * 1_000_003 + it)
        total = None
        for grp in groups:
            batch = None
            if grp.structure == "sparse" and grp.num_points > batch_size:
                batch = torch.randperm(grp.num_points, generator=g)[:batch_size]
                batch = batch.to(grp.train_x.device)
            term = grp.loss(batch)
            total = term if total is None else total + term
        assert total is not None
        return total

    prog = Progress(type(model).__name__, iterations) if progress else None
    natural = [
        (g.variational_parameters(), g.num_points) for g in groups if g.structure == "sparse"
    ]
    skip = {id(p) for ps, _ in natural for p in ps}
    adam = [p for p in model.parameters() if id(p) not in skip]
    if fixed:  # held fixed: left out of Adam (names checked by free_parameters)
        adam = free_parameters(model, adam, fixed)
    try:
        return run_adam(
            adam,
            loss_fn,
            natural=natural,
            natural_lr=natural_lr,
            iterations=iterations,
            lr=lr,
            start=start,
            optimizer_state=optimizer_state,
            callback=callback,
            progress=prog,
            model=model,
        )
    finally:
        for grp in groups:
            grp.use_rows(None)


def load_checkpoint(model: Any, ckpt: dict[str, Any]) -> tuple[int, dict[str, Any]]:
    """Load a checkpoint from :meth:`FitState.checkpoint` into ``model`` (a
    :class:`~torchfilt.models.gp.GPModel` with the same options and data).

    Returns:
        The iterations done and the optimiser states.

    Raises:
        InputError: not such a checkpoint, other options or other data.
    """
    if not isinstance(ckpt, dict) or not {"model", "optimizer", "iteration"} <= set(ckpt):
        raise InputError("resume: expected a checkpoint from FitState.checkpoint()")
    state = ckpt["model"]
    if state.get("config") != model.config.to_dict():
        mine, theirs = model.config.to_dict(), state.get("config") or {}
        diff = sorted(k for k in set(mine) | set(theirs) if mine.get(k) != theirs.get(k))
        raise InputError(f"resume: the checkpoint's model options differ in {diff}")
    sd = state["state_dict"]
    own = model.state_dict()
    for k, v in own.items():
        if k.endswith(("train_x", "train_y")) and (k not in sd or not torch.equal(sd[k], v)):
            raise InputError("resume: the checkpoint was trained on different data")
    model.load_state_dict(sd)
    return int(ckpt["iteration"]), ckpt["optimizer"]
