"""The fitting loop: one iteration after another, with progress, the user's callback, the
data-parallel stop, stopping rules and checkpoints, around a step that the fit supplies.

A fit (the likelihood fit, EM, a GP's hyperparameters) writes only its *step*: what one
iteration does (an optimiser step, an E- and an M-step), returning an :class:`Outcome`.
:class:`FitLoop` does everything around it, in this order at every iteration:

1. the step (an :class:`Outcome` with ``abort`` ends the loop at once; one without a
   ``record`` is an iteration that does not count: no record, callback or checkpoint);
2. the record is appended to the history; the progress reporter shows ``info``;
3. the callback sees ``state``; in a data-parallel fit (``all_reduce``) one process's stop
   stops all (one collective);
4. the stopping rules: the step's own ``done``, then early stopping on held-out data
   (:class:`EarlyStopping`, after ``patience`` evaluations without improvement), then
   convergence: the loss changed by less than ``tol * (1 + |loss|)`` in one iteration, or by
   at most ``rtol * max(1, |L_k|)`` over the last ``rtol_window`` iterations
   (``|L_k - L_{k-w}|``; on by default, see :class:`~torchfilt.optim.StoppingOptions`), or
   the objective improved by less than ``atol`` (in its own units, e.g. nats per recording)
   over those iterations;
5. a checkpoint every ``every`` iterations, at the last one and when a rule stopped the fit:
   the loop's state (iteration, history, the stop reason, the early-stopping state) and the
   fit's own entries, written atomically; a fit resumed from it continues exactly where the
   uninterrupted one would (a fit that had stopped by itself stays stopped).

:class:`GuardedStep` is the optimiser step of the gradient fits: Adam or L-BFGS
(:func:`make_optimizer`), never leaving the finite region (a non-finite loss or parameter
restores the last good parameters; L-BFGS then forgets its curvature once and tries again; an
L-BFGS line search that ran into the non-finite region and found no lower loss, so that the
parameters did not move, shortens the learning rate tenfold and tries again, at most
:attr:`GuardedStep.SHRINKS` times: a badly scaled problem, where one parameter's gradient is many
orders of magnitude another's, would otherwise end at its start, reported as converged).
:func:`failed_step` turns a factorisation that failed inside a fit's step (a user's model that
calls ``torch.linalg.cholesky``) into a :class:`~torchfilt.exceptions.FitError` naming the fit
and the step.
"""

from __future__ import annotations

import math
import time
import warnings
from collections.abc import Callable, Iterable, Iterator, Sequence
from contextlib import contextmanager
from typing import Any, Literal, NamedTuple, Protocol

import torch
from torch import Tensor

from torchfilt.exceptions import ConvergenceWarning, FitError, InputError, InputTypeError
from torchfilt.optim.checkpoint import CheckpointFile
from torchfilt.optim.options import OptimizerOptions, StoppingOptions

__all__ = [
    "EarlyStopping",
    "FitLoop",
    "GuardedStep",
    "Outcome",
    "Reporter",
    "StepResult",
    "failed_step",
    "free_parameters",
    "make_optimizer",
    "restore",
    "snapshot",
]


class Reporter(Protocol):
    """Shows progress (e.g. :class:`torchfilt.io.progress.ProgressBar`)."""

    def update(self, done: int, info: str = "") -> None:
        """Report progress.

        Args:
            done: iterations done so far.
            info: a short status text shown with the count.
        """
        ...


def snapshot(params: Iterable[Tensor]) -> list[Tensor]:
    """Detached copies of ``params``.

    Args:
        params: the parameters, each of any shape.

    Returns:
        A detached copy of each parameter, each of its parameter's shape (any shape).
    """
    return [p.detach().clone() for p in params]


def restore(params: Sequence[Tensor], values: Sequence[Tensor]) -> None:
    """Copy ``values`` into ``params`` in place (no gradient).

    Args:
        params: the parameters, each of any shape.
        values: one value per parameter, each of any shape that broadcasts to its parameter's.
    """
    with torch.no_grad():
        for p, v in zip(params, values, strict=True):
            p.copy_(v)


def free_parameters(
    module: torch.nn.Module,
    params: Iterable[torch.nn.Parameter] | None = None,
    fixed: Iterable[str] = (),
    *,
    what: str = "params",
) -> list[torch.nn.Parameter]:
    """The parameters a fit steps: ``params`` (default: every parameter of ``module``) with
    ``requires_grad``, less those named in ``fixed`` (names as ``module.named_parameters()``
    gives them), which the fit then leaves bit-identical.

    Raises:
        InputError: a name in ``fixed`` that is no parameter of ``module`` (named), or nothing
            left to fit.
    """
    if isinstance(fixed, str):
        raise InputTypeError(f"fixed: expected a collection of names, got the string {fixed!r}")
    named = dict(module.named_parameters())
    unknown = [name for name in fixed if name not in named]
    if unknown:
        raise InputError(
            f"fixed: {unknown[0]!r} is no parameter of the model (its parameters: "
            f"{sorted(named)[:12]})"
        )
    held = {id(named[name]) for name in fixed}
    source = module.parameters() if params is None else params
    plist = [p for p in source if p.requires_grad and id(p) not in held]
    if not plist:
        raise InputError(
            f"{what}: nothing to fit (no parameter with requires_grad"
            + (", less the fixed ones)" if held else ")")
        )
    return plist


@contextmanager
def failed_step(fit: str, step: str | Callable[[], str]) -> Iterator[None]:
    """Run a step of a fit, turning a failed factorisation in it (``torch.linalg.LinAlgError``:
    a Cholesky or solve of a matrix that is singular even with jitter, typically inside a
    user's model) into a :class:`~torchfilt.exceptions.FitError` naming the fit and the step.

    Args:
        fit: the fit's name, e.g. ``"fit_em"``.
        step: the step in words, e.g. ``"iteration 3, E-step"``, or a function that says it
            when the failure happens (a step whose part under way changes as it runs).

    Raises:
        FitError: the step raised ``torch.linalg.LinAlgError``.
    """
    try:
        yield
    except torch.linalg.LinAlgError as e:
        step = step if isinstance(step, str) else step()
        raise FitError(
            f"{fit}: {step}: a matrix factorisation failed ({str(e).splitlines()[0]}); the "
            "parameters left the region where the model is defined. Start closer to the data "
            "(smaller steps or learning rate, bounded hyperparameters) or use torchfilt's "
            "safe_cholesky in the model",
            fit=fit,
            step=step,
        ) from e


def make_optimizer(params: Sequence[Tensor], options: OptimizerOptions) -> torch.optim.Optimizer:
    """The optimiser of ``options`` over ``params``: Adam, or L-BFGS with a strong-Wolfe line
    search and the options' tolerances.

    Args:
        params: the parameters to step, each of any shape.
        options: the optimiser and its settings.

    Returns:
        The ``torch.optim`` optimiser.
    """
    lr = options.learning_rate
    if options.optimizer == "adam":
        return torch.optim.Adam(list(params), lr=lr)
    return torch.optim.LBFGS(
        list(params),
        lr=lr,
        max_iter=options.max_iter,
        line_search_fn="strong_wolfe",
        tolerance_change=options.tolerance_change,
        tolerance_grad=options.tolerance_grad,
        history_size=options.history_size,
    )


class StepResult(NamedTuple):
    """What :class:`GuardedStep` returns.

    Attributes:
        loss: the loss the step evaluated (at the parameters before it; NaN after a failed
            L-BFGS search).
        loss_finite: whether ``loss`` is finite.
        good: the parameters ``loss`` scores (before the step) when it is finite; else the last
            parameters scored finite (where a failed step leaves them); each of any shape (its
            parameter's).
        status: ``"ok"``; ``"retry"`` (L-BFGS left the finite region, or its line search met
            only non-finite or higher losses and did not move: the parameters are back at
            ``good``, its curvature is forgotten, the iteration does not count); ``"failed"``
            (non-finite again: the parameters are back at ``good``).
    """

    loss: float
    loss_finite: bool
    good: list[Tensor]
    status: Literal["ok", "retry", "failed"]


class GuardedStep:
    """One optimiser iteration over ``params`` that never leaves the finite region.

    Args:
        params: the parameters, each of any shape.
        options: the optimiser.
        project: called after every step to project the parameters back onto their feasible set
            in place.

    An L-BFGS step whose line search evaluated a non-finite loss and left the parameters where
    they were shortens the optimiser's learning rate tenfold (kept for the rest of the fit, and
    in its checkpoint, as the optimiser's state) and is retried, down to ``10 ** -SHRINKS`` of
    the learning rate it started with.
    """

    #: tenfold shortenings of the L-BFGS learning rate after a stalled line search
    SHRINKS = 3

    def __init__(
        self,
        params: Sequence[Tensor],
        options: OptimizerOptions,
        project: Callable[[], None] | None = None,
    ) -> None:
        self.params, self.options, self.project = list(params), options, project
        self.optimizer = make_optimizer(self.params, options)
        self.retried = False
        self.good: list[Tensor] | None = None  # the last parameters scored finite

    def __call__(self, closure: Callable[[], Tensor]) -> StepResult:
        """Step with ``closure`` (zeroes the gradients, returns the loss, ``+inf`` where it is not
        finite, after its backward pass)."""
        opt = self.optimizer
        if self.good is None:
            self.good = snapshot(self.params)
        if self.options.optimizer == "adam":
            loss_t = closure()
            finite = bool(torch.isfinite(loss_t))
            if finite:
                self.good = snapshot(self.params)  # the parameters that loss_t scores
                opt.step()
                if self.project is not None:
                    self.project()
        else:
            self.good = snapshot(self.params)
            met_non_finite = [False]  # by an evaluation of this step's line search

            def counted() -> Tensor:
                value = closure()
                met_non_finite[0] |= not bool(torch.isfinite(value))
                return value

            try:
                loss_t = opt.step(counted)  # type: ignore[assignment,arg-type]
            except IndexError:
                # torch's strong-Wolfe search fails when every trial step was non-finite (and
                # the same on every process of a data-parallel fit: the loss is their sum)
                loss_t = torch.tensor(math.nan)
            if self.project is not None:
                self.project()
            finite = bool(torch.isfinite(loss_t))
            if finite and met_non_finite[0] and self._stalled() and self._shorten():
                # the search met only non-finite or higher losses and stayed at the start
                opt.state.clear()
                return StepResult(float(loss_t), True, self.good, "retry")
        loss = float(loss_t)
        loss_finite, good = finite, self.good
        finite = finite and all(bool(torch.isfinite(p).all()) for p in self.params)
        if finite:
            self.retried = False
            return StepResult(loss, loss_finite, good, "ok")
        restore(self.params, good)
        if self.options.optimizer == "lbfgs" and (not self.retried or self._shorten()):
            # a line search that left the finite region: forget the curvature history and start
            # again from the last good parameters with a short first step (again: a shorter
            # learning rate)
            self.retried = True
            opt.state.clear()
            return StepResult(loss, loss_finite, good, "retry")
        return StepResult(loss, loss_finite, good, "failed")

    def _stalled(self) -> bool:
        """Whether the parameters are exactly where the step started (``good``)."""
        assert self.good is not None
        return all(torch.equal(p.detach(), g) for p, g in zip(self.params, self.good, strict=True))

    def _shorten(self) -> bool:
        """Shorten the L-BFGS learning rate tenfold, unless it is already ``10 ** -SHRINKS`` of
        the options' (then ``False``)."""
        floor = self.options.learning_rate * 10.0 ** (-self.SHRINKS) * (1 + 1e-9)
        groups = self.optimizer.param_groups
        if any(float(g["lr"]) <= floor for g in groups):
            return False
        for g in groups:
            g["lr"] = float(g["lr"]) * 0.1
        return True


class EarlyStopping:
    """Early stopping on held-out data: the best held-out score and its parameters, and the
    evaluations since it improved.

    Args:
        options: ``patience`` and ``validate_every``.
        score: the held-out score (higher is better), or ``None`` (no held-out data: never
            exhausted, the best stays the start).
        snapshot: the current parameters (copies), kept at the best score.
        patience_given: the caller set ``patience`` (not the fit's default): without held-out
            data, early stopping cannot act, which then warns.
    """

    def __init__(
        self,
        options: StoppingOptions,
        score: Callable[[], float] | None,
        snapshot: Callable[[], list[Tensor]],
        *,
        patience_given: bool = False,
    ) -> None:
        self.options, self.score, self.snapshot = options, score, snapshot
        self.patience = 20 if options.patience is None else int(options.patience)
        if score is None and patience_given:
            warnings.warn(
                f"patience={options.patience} was given but there is no held-out data "
                "(validation=None): early stopping cannot act; the fit stops at convergence or "
                "its iteration budget. Give validation data to stop on held-out likelihood",
                ConvergenceWarning,
                stacklevel=3,
            )
        self.bad, self.best_iteration, self.best_score = 0, 0, -math.inf
        self.best_params = snapshot()

    def observe(self, iteration: int) -> float | None:
        """Evaluate the held-out score when ``iteration`` is due (``None`` otherwise)."""
        if self.score is None or iteration % self.options.validate_every != 0:
            return None
        value = self.score()
        if value > self.best_score:
            self.best_iteration, self.best_score, self.bad = iteration, value, 0
            self.best_params = self.snapshot()
        else:
            self.bad += 1
        return value

    @property
    def exhausted(self) -> bool:
        """``patience`` evaluations in a row without improvement."""
        return self.score is not None and self.bad >= self.patience

    def state_dict(self) -> dict[str, Any]:
        """The checkpoint entries."""
        return {
            "bad": self.bad,
            "best_iteration": self.best_iteration,
            "best_score": self.best_score,
            "best_params": self.best_params,
        }

    def load_state_dict(self, ck: dict[str, Any]) -> None:
        """Restore from a checkpoint's entries."""
        self.bad, self.best_iteration = int(ck["bad"]), int(ck["best_iteration"])
        self.best_score = float(ck["best_score"])
        self.best_params = [t.clone() for t in ck["best_params"]]


class Outcome(NamedTuple):
    """What a fit's step returns for one iteration.

    Attributes:
        record: the iteration's history record (``None``: the iteration does not count).
        state: what the user's callback sees.
        info: progress text.
        done: the step's own reason to stop after this iteration (checkpointed; ``None``: go on).
        abort: stop at once, before recording (e.g. ``"non-finite"``).
    """

    record: dict[str, Any] | None
    state: Any = None
    info: str = ""
    done: str | None = None
    abort: str | None = None


class FitLoop:
    """The loop around a fit's step (see the module docstring).

    Args:
        iterations: the budget (counting the iterations of a resumed run).
        progress: shows ``info`` after every counted iteration (``None``: silent).
        callback: sees each counted iteration's ``state``; ``True`` stops.
        all_reduce: of a data-parallel fit: sums a flat float64 tensor in place across the
            processes (a stop by one process's callback stops all).
        stopping: early stopping on held-out data (checkpointed with the loop).
        tol: convergence: stop when the record's ``loss`` changed by less than
            ``tol * (1 + |loss|)`` since the previous record (0: off).
        rtol: convergence over a window: stop when ``|L_k - L_{k-w}| <= rtol * max(1, |L_k|)``
            for the records' ``loss`` ``L`` (0: off).
        rtol_window: the window ``w`` of ``rtol`` and ``atol``.
        atol: convergence over the window in the objective's own units: stop when
            ``(L_{k-w} - L_k) * scale < atol`` (the objective improved by less than ``atol``;
            0: off).
        scale: the units of ``atol`` per unit of the records' loss (e.g. measurements per
            recording for a loss per measurement and ``atol`` in nats per recording; 0: off).
        monitor: the record entry the convergence rules watch. Records without it (iterations
            whose objective was not evaluated) are skipped: the rules compare the last record
            that has it with the one before it (``tol``) and with the latest one at least ``w``
            records earlier (``rtol``, ``atol``), and act only at a record that has it.
        checkpoint: the checkpoint file (``None``: none).
        every: iterations between checkpoints.
        start: iterations already done (a run resumed by its caller, without a checkpoint file).
    """

    def __init__(
        self,
        *,
        iterations: int,
        progress: Reporter | None = None,
        callback: Callable[[Any], bool | None] | None = None,
        all_reduce: Callable[[Tensor], None] | None = None,
        stopping: EarlyStopping | None = None,
        tol: float = 0.0,
        rtol: float = 0.0,
        rtol_window: int = 20,
        atol: float = 0.0,
        scale: float = 0.0,
        monitor: str = "loss",
        checkpoint: CheckpointFile | None = None,
        every: int = 1,
        start: int = 0,
    ) -> None:
        self.iterations, self.progress, self.callback = iterations, progress, callback
        self.all_reduce, self.stopping, self.tol = all_reduce, stopping, tol
        self.rtol, self.rtol_window = rtol, max(1, int(rtol_window))
        self.atol, self.scale, self.monitor = atol, scale, monitor
        self.checkpoint, self.every = checkpoint, every
        self.iteration = start  # the last iteration started (or resumed from)
        self.history: list[dict[str, Any]] = []
        self.done: str | None = None  # why a resumed fit had stopped by itself

    def resume(self) -> dict[str, Any] | None:
        """Continue from the checkpoint, if there is one: the loop's state is restored and the
        checkpoint returned for the fit's own entries (``None``: start afresh)."""
        ck = None if self.checkpoint is None else self.checkpoint.resume()
        if ck is not None:
            self.iteration, self.history = int(ck["iteration"]), list(ck["history"])
            self.done = ck.get("done")
            if self.stopping is not None:
                self.stopping.load_state_dict(ck)
        return ck

    def run(
        self,
        step: Callable[[int], Outcome],
        payload: Callable[[], dict[str, Any]] | None = None,
    ) -> str:
        """Run ``step`` from the iteration after the current one to the budget.

        Args:
            step: one iteration, given its number (1-based).
            payload: the fit's own checkpoint entries (its parameters, optimiser state, ...).

        Returns:
            Why the loop ended: ``"iterations"``, ``"callback"``, ``"early stopping"``,
            ``"converged"``, the step's ``done`` or ``abort``, or the resumed fit's stop reason.
        """
        if self.done is not None:
            return self.done
        t0, first = time.perf_counter(), self.iteration
        for it in range(self.iteration + 1, self.iterations + 1):
            self.iteration = it
            out = step(it)
            if out.abort is not None:
                return out.abort
            if out.record is None:
                continue
            self.history.append(out.record)
            if self.progress is not None:
                self.progress.update(it, out.info + self._eta(it, first, t0))
            stop = bool(self.callback(out.state)) if self.callback is not None else False
            if self.all_reduce is not None:
                flat = torch.tensor([float(stop)], dtype=torch.float64)
                self.all_reduce(flat)
                stop = bool(flat[0] > 0)
            done = out.done or self._rule()
            if self.checkpoint is not None and (
                it % self.every == 0 or it == self.iterations or done is not None
            ):
                self.checkpoint.save(self._payload(it, done, payload))
            if stop:
                return "callback"
            if done is not None:
                return done
        return "iterations"

    #: counted iterations before the first estimate of the stage's time
    ETA_AFTER = 3

    def _eta(self, it: int, first: int, t0: float) -> str:
        """The estimated time of the stage and what is left, after the first few iterations
        (the rate of this run's iterations, resumed ones excluded). Drawn by the fit's own
        reporter, not tqdm: the core dependencies are torch, gpytorch, numpy and matplotlib,
        and a progress line is not worth another."""
        done = it - first
        if done < self.ETA_AFTER:
            return ""
        rate = (time.perf_counter() - t0) / done
        total, left = rate * (self.iterations - first), rate * (self.iterations - it)
        return f" | stage ~{_seconds(total)}, eta {_seconds(left)}"

    def _rule(self) -> str | None:
        if self.stopping is not None and self.stopping.exhausted:
            return "early stopping"
        hist, key = self.history, self.monitor
        if not hist or key not in hist[-1]:
            return None
        loss = float(hist[-1][key])
        if self.tol > 0:
            j = self._before(len(hist) - 2)
            if j is not None and abs(float(hist[j][key]) - loss) <= self.tol * (1 + abs(loss)):
                return "converged"
        w = self.rtol_window
        j = self._before(len(hist) - 1 - w)
        if j is None:
            return None
        then = float(hist[j][key])
        if self.rtol > 0 and abs(loss - then) <= self.rtol * max(1.0, abs(loss)):
            return "converged"
        if self.atol > 0 and self.scale > 0 and (then - loss) * self.scale < self.atol:
            return "converged"
        return None

    def _before(self, index: int) -> int | None:
        """The last record at or before ``index`` that has the monitored entry."""
        for j in range(index, -1, -1):
            if self.monitor in self.history[j]:
                return j
        return None

    def _payload(
        self, it: int, done: str | None, payload: Callable[[], dict[str, Any]] | None
    ) -> dict[str, Any]:
        data: dict[str, Any] = {"iteration": it, "history": self.history, "done": done}
        if self.stopping is not None:
            data.update(self.stopping.state_dict())
        if payload is not None:
            data.update(payload())
        return data


def _seconds(t: float) -> str:
    """``t`` seconds as ``12s``, ``3.5min`` or ``1.2h``."""
    if not math.isfinite(t):
        return "?"
    if t < 90:
        return f"{t:.0f}s"
    if t < 5400:
        return f"{t / 60:.1f}min"
    return f"{t / 3600:.1f}h"
