"""The fitting loop of every fit (``torchfilt.optim``) on tiny least-squares problems whose
solution is known in closed form: both optimisers reach it, the stopping rules stop where they
should, a killed and resumed fit equals an uninterrupted one bit for bit, and the callback and the
data-parallel hook see every iteration."""

from __future__ import annotations

import math
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest
import torch

from torchfilt.exceptions import InputError, RunError
from torchfilt.io import atomic_write
from torchfilt.optim import (
    DEFAULTS,
    CheckpointFile,
    CheckpointOptions,
    EarlyStopping,
    FitLoop,
    GuardedStep,
    OptimizerOptions,
    Outcome,
    StoppingOptions,
    WindowOptions,
    fingerprint,
    snapshot,
)


def problem(seed: int = 0) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """``A (20, 3)``, ``b (20,)`` and the least-squares solution ``x* = argmin |A x - b|^2``."""
    gen = torch.Generator().manual_seed(seed)
    A = torch.randn(20, 3, generator=gen, dtype=torch.float64)
    b = A @ torch.tensor([1.0, -2.0, 0.5], dtype=torch.float64)
    b = b + 0.1 * torch.randn(20, generator=gen, dtype=torch.float64)
    x_star = torch.linalg.lstsq(A, b.unsqueeze(-1)).solution.squeeze(-1)
    return A, b, x_star


class Killed(Exception):
    pass


def fit(
    optimizer: str = "adam",
    iterations: int = 50,
    *,
    lr: float | None = None,
    checkpoint: Path | None = None,
    every: int = 3,
    resume: bool = False,
    kill_at: int | None = None,
    score: Any = None,
    patience: int = 3,
    tol: float = 0.0,
    all_reduce: Any = None,
    seen: list | None = None,
) -> tuple[str, torch.Tensor, FitLoop, EarlyStopping]:
    A, b, _ = problem()
    x = torch.zeros(3, dtype=torch.float64, requires_grad=True)
    guarded = GuardedStep([x], OptimizerOptions(optimizer, lr=lr))  # type: ignore[arg-type]
    early = EarlyStopping(StoppingOptions(patience=patience), score, lambda: snapshot([x]))
    ck = None
    if checkpoint is not None:
        ck = CheckpointFile(
            checkpoint, fingerprint(A, b, x), schema="test/1", kind="test", write=atomic_write
        )

    def callback(state: tuple[int, float]) -> bool:
        if seen is not None:
            seen.append(state)
        if state[0] == kill_at:
            raise Killed  # a process killed after iteration kill_at
        return False

    loop = FitLoop(
        iterations=iterations,
        callback=callback,
        all_reduce=all_reduce,
        stopping=early,
        tol=tol,
        checkpoint=ck,
        every=every,
    )
    if resume:
        got = loop.resume()
        if got is not None:
            with torch.no_grad():
                x.copy_(got["x"])
            guarded.optimizer.load_state_dict(got["optimizer"])

    def closure() -> torch.Tensor:
        guarded.optimizer.zero_grad()
        loss = 0.5 * ((A @ x - b) ** 2).mean()
        loss.backward()
        return loss.detach()

    def step(it: int) -> Outcome:
        res = guarded(closure)
        if res.status != "ok":
            return Outcome(None, abort="non-finite")
        early.observe(it)
        return Outcome({"iteration": it, "loss": res.loss}, (it, res.loss))

    def payload() -> dict[str, Any]:
        return {"x": x.detach().clone(), "optimizer": guarded.optimizer.state_dict()}

    stopped = loop.run(step, payload)
    return stopped, x.detach(), loop, early


@pytest.mark.parametrize("optimizer", ["adam", "lbfgs"])
def test_both_optimisers_reach_the_closed_form(optimizer):
    _, _, x_star = problem()
    iterations = 3000 if optimizer == "adam" else 5
    stopped, x, loop, _ = fit(optimizer, iterations, lr=0.05 if optimizer == "adam" else None)
    assert stopped == "iterations" and len(loop.history) == iterations
    tol = 1e-6 if optimizer == "adam" else 1e-8  # L-BFGS: to the loss's resolution
    assert torch.allclose(x, x_star, atol=tol, rtol=0), (x, x_star)
    # the loss decreased (the loss at the start is at x = 0)
    assert loop.history[-1]["loss"] < loop.history[0]["loss"]


def test_convergence_rule_stops_lbfgs():
    _, _, x_star = problem()
    stopped, x, loop, _ = fit("lbfgs", 50, tol=1e-12)
    assert stopped == "converged" and len(loop.history) < 50
    assert torch.allclose(x, x_star, atol=1e-8, rtol=0)


def test_early_stopping_stops_at_patience():
    # held-out scores rise for 4 evaluations, then fall: the best is iteration 4, and with
    # patience 3 the fit stops 3 evaluations later, keeping the parameters of iteration 4
    scores = iter([1.0, 2.0, 3.0, 4.0, 3.9, 3.8, 3.7, 3.6, 3.5])
    seen: list = []
    stopped, _, loop, early = fit("adam", 30, score=lambda: next(scores), patience=3, seen=seen)
    assert stopped == "early stopping"
    assert len(loop.history) == 7 and early.best_iteration == 4 and early.best_score == 4.0
    assert early.bad == 3
    # the kept parameters are those after iteration 4: rerun 4 iterations without held-out data
    _, x4, _, _ = fit("adam", 4)
    assert torch.equal(early.best_params[0], x4)
    assert [s[0] for s in seen] == list(range(1, 8))


@pytest.mark.parametrize("optimizer", ["adam", "lbfgs"])
@pytest.mark.parametrize("kill_at", [4, 6])
def test_killed_and_resumed_equals_uninterrupted(tmp_path, optimizer, kill_at):
    iterations = 10 if optimizer == "adam" else 4
    kill_at = min(kill_at, iterations - 1) if optimizer == "adam" else kill_at // 2
    _, x_straight, straight, _ = fit(optimizer, iterations)
    path = tmp_path / "fit.ckpt"
    with pytest.raises(Killed):
        fit(optimizer, iterations, checkpoint=path, every=3 if optimizer == "adam" else 1,
            kill_at=kill_at)  # fmt: skip
    saved = torch.load(path, weights_only=True)
    assert 0 < saved["iteration"] < kill_at  # the killed iterations after it are redone
    stopped, x_resumed, resumed, _ = fit(
        optimizer, iterations, checkpoint=path, every=3 if optimizer == "adam" else 1, resume=True
    )
    assert stopped == "iterations"
    assert torch.equal(x_resumed, x_straight)  # bit for bit
    assert [h["loss"] for h in resumed.history] == [h["loss"] for h in straight.history]
    # the last checkpoint is the last iteration's
    assert torch.load(path, weights_only=True)["iteration"] == iterations


def test_a_fit_that_stopped_by_itself_stays_stopped_on_resume(tmp_path):
    path = tmp_path / "fit.ckpt"
    stopped, x, loop, _ = fit("lbfgs", 50, tol=1e-12, checkpoint=path, every=100)
    assert stopped == "converged"
    ck = torch.load(path, weights_only=True)
    assert ck["done"] == "converged" and ck["iteration"] == len(loop.history)
    again, x2, loop2, _ = fit("lbfgs", 50, tol=1e-12, checkpoint=path, every=100, resume=True)
    assert again == "converged" and torch.equal(x, x2) and len(loop2.history) == len(loop.history)


def test_a_checkpoint_of_another_fit_is_refused(tmp_path):
    path = tmp_path / "fit.ckpt"
    fit("adam", 3, checkpoint=path)
    other = CheckpointFile(path, "another", schema="test/1", kind="test", write=atomic_write)
    with pytest.raises(RunError, match="another fit"):
        other.resume()
    wrong = CheckpointFile(path, "x", schema="other/1", kind="EM", write=atomic_write)
    with pytest.raises(RunError, match="not a torchfilt EM checkpoint"):
        wrong.load()


def test_callback_sees_every_iteration_and_its_loss():
    _, b, _ = problem()
    seen: list = []
    _, _, loop, _ = fit("adam", 5, seen=seen)
    assert [s[0] for s in seen] == [1, 2, 3, 4, 5]
    # the loss of iteration k is the objective at the parameters before its step: at x = 0 first
    assert seen[0][1] == pytest.approx(float(0.5 * (b**2).mean()), rel=1e-14)
    assert [s[1] for s in seen] == [h["loss"] for h in loop.history]


def test_all_reduce_is_called_and_another_process_can_stop_all():
    calls: list[torch.Tensor] = []

    def alone(flat: torch.Tensor) -> None:  # a world of one process
        calls.append(flat.clone())

    stopped, _, loop, _ = fit("adam", 6, all_reduce=alone)
    assert stopped == "iterations" and len(calls) == 6
    assert all(c.dtype == torch.float64 and c.shape == (1,) and float(c[0]) == 0 for c in calls)

    calls.clear()

    def other_stops_at_3(flat: torch.Tensor) -> None:  # another process's callback stops at 3
        calls.append(flat.clone())
        if len(calls) == 3:
            flat += 1.0

    stopped, _, loop, _ = fit("adam", 6, all_reduce=other_stops_at_3)
    assert stopped == "callback" and len(loop.history) == 3


def test_guarded_step_never_leaves_the_finite_region():
    # Adam: the objective is non-finite below 0.88; the failed step restores the parameters
    # before the last step that was scored finite
    x = torch.tensor([1.0], dtype=torch.float64, requires_grad=True)
    guarded = GuardedStep([x], OptimizerOptions("adam"))

    def closure() -> torch.Tensor:
        guarded.optimizer.zero_grad()
        if float(x.detach()) < 0.88:
            return torch.tensor(math.inf, dtype=torch.float64)
        loss = (x**2).sum()
        loss.backward()
        return loss.detach()

    before = []
    for _ in range(10):
        before.append(x.detach().clone())
        res = guarded(closure)
        if res.status != "ok":
            break
    assert res.status == "failed" and not res.loss_finite
    assert torch.equal(x.detach(), before[-2]) and float(x.detach()) >= 0.88
    # L-BFGS: a non-finite iteration is retried with its curvature forgotten, then with the
    # learning rate shortened tenfold SHRINKS times, then fails
    y = torch.tensor([1.0], dtype=torch.float64, requires_grad=True)
    lbfgs = GuardedStep([y], OptimizerOptions("lbfgs"))
    inf = lambda: torch.tensor(math.inf, dtype=torch.float64)  # noqa: E731
    statuses = [lbfgs(inf).status for _ in range(GuardedStep.SHRINKS + 2)]
    assert statuses == ["retry"] * (GuardedStep.SHRINKS + 1) + ["failed"]
    assert float(y.detach()) == 1.0
    assert lbfgs.optimizer.param_groups[0]["lr"] == pytest.approx(10.0**-GuardedStep.SHRINKS)


def _badly_scaled(x: torch.Tensor, nan_grad: bool) -> Callable[[], torch.Tensor]:
    """``-log x0 + 1000 x0 + (x1 - 1)^2`` (minimum at ``(1e-3, 1)``), ``+inf`` for ``x0 <= 0``:
    from ``(0.01, 3)`` L-BFGS's first step (the gradient normalised to one unit) lands far
    below 0, and its strong-Wolfe search, which interpolates through ``+inf``, finds nothing.
    ``nan_grad``: the non-finite evaluation leaves a NaN gradient (the search then ends on NaN
    parameters) rather than none (it then ends where it started)."""

    def closure() -> torch.Tensor:
        x.grad = None
        if not bool(x[0].detach() > 0):
            if nan_grad:
                x.grad = torch.full_like(x, math.nan)
            return torch.tensor(math.inf, dtype=torch.float64)
        f = -torch.log(x[0]) + 1e3 * x[0] + (x[1] - 1) ** 2
        f.backward()
        return f.detach()

    return closure


@pytest.mark.parametrize("nan_grad", [False, True])
def test_lbfgs_shortens_its_learning_rate_when_the_search_finds_only_non_finite(nan_grad):
    # before the shortening, both variants stayed at the start for ever: "ok" without a move
    # (then "converged" by the loop's rule) or "failed"
    x = torch.tensor([0.01, 3.0], dtype=torch.float64, requires_grad=True)
    guarded = GuardedStep([x], OptimizerOptions("lbfgs"))
    closure = _badly_scaled(x, nan_grad)
    statuses = [guarded(closure).status for _ in range(12)]
    assert "failed" not in statuses and statuses.count("retry") <= GuardedStep.SHRINKS + 1
    # the minimum of -log x0 + 1000 x0 is x0 = 1 / 1000
    torch.testing.assert_close(
        x.detach(), torch.tensor([1e-3, 1.0], dtype=torch.float64), rtol=1e-3, atol=1e-6
    )


def test_options_are_checked_and_defaults_differ_where_documented():
    with pytest.raises(InputError, match="optimizer"):
        OptimizerOptions("sgd")  # type: ignore[arg-type]
    with pytest.raises(InputError, match="lr"):
        OptimizerOptions(lr=-1.0)
    with pytest.raises(InputError, match="patience"):
        StoppingOptions(patience=0)
    with pytest.raises(InputError, match="start"):
        WindowOptions(start="middle")  # type: ignore[arg-type]
    assert OptimizerOptions("adam").learning_rate == 0.05
    assert OptimizerOptions("lbfgs").learning_rate == 1.0
    assert DEFAULTS["likelihood"].checkpoint.every == 10
    assert DEFAULTS["measurement_only"].checkpoint.every == 1
    assert (
        DEFAULTS["calibrate"].windows.window == 100 and DEFAULTS["calibrate"].windows.burn_in == 20
    )
    assert DEFAULTS["measurement_only"].optimizer.optimizer == "lbfgs"


def test_fit_likelihood_early_stopped_stays_stopped_on_resume(tmp_path):
    """Through ``fit_likelihood``: a fit stopped by its held-out data checkpoints that iteration
    with its reason, and resuming it returns the uninterrupted result without iterating."""
    import ddp_support

    from torchfilt.training import Sequences, fit_likelihood

    def run(resume: bool = False) -> Any:
        model, y, (Q, R) = ddp_support.problem()
        fit = fit_likelihood(
            model,
            y[:4],
            x0=torch.zeros(1, dtype=torch.float64),
            P0=torch.eye(1, dtype=torch.float64),
            validation=Sequences(y[4:]),
            iterations=40,
            optimizer=OptimizerOptions(lr=0.5),
            stopping=StoppingOptions(patience=2),
            checkpoint=CheckpointOptions(tmp_path / "lik.ckpt", every=100, resume=resume),
        )
        return fit, torch.stack([Q().detach().reshape(()), R().detach().reshape(())])

    fit, values = run()
    assert fit.stopped == "early stopping" and fit.iterations < 40
    ck = torch.load(tmp_path / "lik.ckpt", weights_only=True)
    assert ck["done"] == "early stopping" and ck["iteration"] == fit.iterations
    again, values2 = run(resume=True)
    assert again.stopped == "early stopping" and again.history == fit.history
    assert torch.equal(values, values2) and again.log_likelihood == fit.log_likelihood


# ----------------------------------------------------------------------- the rule in nats
def test_atol_rule_stops_at_the_first_window_that_gains_less_than_atol():
    """A loss per measurement falling as ``2^-k``, 100 measurements per recording: the loop
    stops at the first record whose gain over the last ``w`` records, in nats per recording, is
    below ``atol``; a loss falling by a constant step above it never stops."""
    losses = [2.0**-k for k in range(200)]
    loop = FitLoop(iterations=200, atol=0.01, scale=100.0, rtol_window=5)
    assert loop.run(lambda it: Outcome({"loss": losses[it - 1]})) == "converged"
    L = [r["loss"] for r in loop.history]
    assert (L[-6] - L[-1]) * 100 < 0.01 <= (L[-7] - L[-2]) * 100
    steady = FitLoop(iterations=60, atol=0.01, scale=100.0, rtol_window=5)
    assert steady.run(lambda it: Outcome({"loss": -it * 1e-4})) == "iterations"  # 0.05 / window
    assert (
        FitLoop(iterations=60, atol=0.01, rtol_window=5).run(  # no scale: off
            lambda it: Outcome({"loss": 1.0})
        )
        == "iterations"
    )


def test_rules_watch_only_the_records_with_the_monitored_entry():
    """Every third record carries the objective: the rules compare those only (the noisy
    per-iteration ``loss`` never stops the loop)."""
    rng = torch.Generator().manual_seed(0)

    def step(it: int) -> Outcome:
        rec: dict[str, Any] = {"loss": float(torch.rand(1, generator=rng))}
        if it % 3 == 0:
            rec["objective"] = 2.0**-it
        return Outcome(rec)

    loop = FitLoop(iterations=300, atol=0.01, scale=100.0, rtol_window=6, monitor="objective")
    assert loop.run(step) == "converged"
    hist = loop.history
    assert "objective" in hist[-1]
    then = next(r for r in reversed(hist[: len(hist) - 6]) if "objective" in r)
    assert (then["objective"] - hist[-1]["objective"]) * 100 < 0.01
