"""Likelihood fits that stop on a converged objective in nats (``atol``) and step on random
subsets of their windows (``per_iteration``; issue 27 §1/§2): a fit started at its optimum stops
early, one still gaining more than ``atol`` does not, a subset's objective is an unbiased
estimate of the full one, a resumed fit on subsets is bit-identical, and L-BFGS refuses them."""

from __future__ import annotations

import itertools
import math

import pytest
import torch
from torch import nn

import torchfilt
from torchfilt.exceptions import InputError, RecipeError
from torchfilt.models.params import ScalarCovariance
from torchfilt.optim import (
    DEFAULTS,
    CheckpointOptions,
    OptimizerOptions,
    StoppingOptions,
    WindowOptions,
)
from torchfilt.training import calibrate, fit_likelihood
from torchfilt.training.likelihood import Sequences, window_data, window_subset

DT = torch.float64
X0, P0 = torch.zeros(1, dtype=DT), torch.eye(1, dtype=DT)


def simulate(a: float, q: float, r: float, recs: int, T: int, seed: int) -> torch.Tensor:
    """``recs`` AR(1) recordings ``(recs, T, 1)``."""
    g = torch.Generator().manual_seed(seed)
    x, ys = torch.zeros(recs, 1, dtype=DT), []
    for _ in range(T):
        x = a * x + math.sqrt(q) * torch.randn(recs, 1, generator=g, dtype=DT)
        ys.append(x + math.sqrt(r) * torch.randn(recs, 1, generator=g, dtype=DT))
    return torch.stack(ys, 1)


class Gain(nn.Module):
    def __init__(self, a: float) -> None:
        super().__init__()
        self.A = nn.Parameter(torch.tensor([[a]], dtype=DT))

    def forward(self, x: torch.Tensor, u: torch.Tensor | None = None) -> torch.Tensor:
        return x @ self.A.mT


def ar1(a: float = 0.5, q: float = 1.0, r: float = 1.0) -> torchfilt.StateSpaceModel:
    return torchfilt.StateSpaceModel(
        Gain(a),
        lambda x, u: x,
        Q=ScalarCovariance(q, 1, dtype=DT),
        R=ScalarCovariance(r, 1, dtype=DT),
    )


def state(model: torchfilt.StateSpaceModel) -> list[torch.Tensor]:
    return [p.detach().clone() for p in model.parameters()]


# ----------------------------------------------------------------------------- atol
def test_atol_defaults_and_checks():
    assert StoppingOptions().atol == 0.01
    assert DEFAULTS["calibrate"].windows.per_iteration == 64
    assert DEFAULTS["likelihood"].windows.per_iteration == "auto"  # every window, resolved
    with pytest.raises(InputError, match="atol"):
        StoppingOptions(atol=-1.0)
    with pytest.raises(InputError, match="per_iteration"):
        WindowOptions(per_iteration=0)
    with pytest.raises(InputError, match="full_every"):
        WindowOptions(full_every=0)


def test_a_fit_started_at_its_optimum_stops_early_in_nats():
    """The optimum by L-BFGS to its tight tolerance; Adam started there gains nothing: the atol
    rule stops it after one window of iterations (the relative rule, off here, would not), and
    with atol = 0 it runs its budget."""
    y = simulate(0.8, 0.5, 0.3, 4, 40, seed=0)
    model = ar1()
    fit_likelihood(
        model, y, x0=X0, P0=P0, optimizer="lbfgs", iterations=30,
        stopping=StoppingOptions(atol=0.0),
    )  # fmt: skip
    opt = state(model)
    kw = dict(x0=X0, P0=P0, optimizer=OptimizerOptions(lr=1e-3), iterations=40)
    at = dict(rtol=0.0, rtol_window=20)
    m1 = ar1()
    with torch.no_grad():
        for p, v in zip(m1.parameters(), opt, strict=True):
            p.copy_(v)
    fit = fit_likelihood(m1, y, stopping=StoppingOptions(**at), **kw)
    assert fit.stopped == "converged" and fit.iterations == 21
    L = [h["loss"] for h in fit.history]
    assert (L[-21] - L[-1]) * fit.measurements / 4 < 0.01
    m2 = ar1()
    with torch.no_grad():
        for p, v in zip(m2.parameters(), opt, strict=True):
            p.copy_(v)
    assert (
        fit_likelihood(m2, y, stopping=StoppingOptions(atol=0.0, **at), **kw).stopped
        == "iterations"
    )


def test_a_fit_still_gaining_more_than_atol_runs_on():
    """Far from its optimum, every window of 20 iterations gains more than atol nats per
    recording: the fit runs its whole budget."""
    y = simulate(0.8, 0.5, 0.3, 4, 40, seed=0)
    fit = fit_likelihood(
        ar1(a=0.0, q=3.0, r=3.0),
        y,
        x0=X0,
        P0=P0,
        optimizer=OptimizerOptions(lr=0.005),
        iterations=30,
        stopping=StoppingOptions(rtol=0.0, atol=0.01),
    )
    assert fit.stopped == "iterations" and fit.iterations == 30
    L = [h["loss"] for h in fit.history]
    gains = [(L[k - 20] - L[k]) * fit.measurements / 4 for k in range(20, 30)]
    assert min(gains) > 0.01


# ----------------------------------------------------------------------------- subsets
def test_window_subset_is_a_deterministic_uniform_draw():
    a = window_subset(10, 4, seed=3, iteration=7)
    assert torch.equal(a, window_subset(10, 4, seed=3, iteration=7))
    assert a.tolist() == sorted(set(a.tolist())) and len(a) == 4
    assert not all(torch.equal(a, window_subset(10, 4, 3, it)) for it in range(8, 12))
    with pytest.raises(InputError, match="size"):
        window_subset(3, 4, 0, 1)


def test_subset_objectives_average_to_the_full_one():
    """Five whole recordings (one window each), two per iteration: the fit's first loss is
    ``windows / 2`` times the two drawn recordings' log-likelihood (each filtered alone, the
    reference), and the mean over all ten pairs is exactly the full objective."""
    y = simulate(0.8, 0.5, 0.3, 5, 30, seed=1)
    model = ar1()
    with torch.no_grad():
        ref = torch.stack(
            [torchfilt.CKF(model).filter(y[i], x0=X0, P0=P0).log_likelihood for i in range(5)]
        )
    counted = 5 * 30
    for seed in range(6):
        fit = fit_likelihood(
            ar1(),
            y,
            x0=X0,
            P0=P0,
            windows=WindowOptions(per_iteration=2, seed=seed),
            iterations=1,
            progress=False,
        )
        drawn = window_subset(5, 2, seed, 1)
        want = -2.5 * float(ref[drawn].sum()) / counted
        assert fit.history[0]["loss"] == pytest.approx(want, rel=1e-12, abs=0)
        assert fit.initial_log_likelihood == pytest.approx(float(ref.sum()), rel=1e-12)
    pairs = list(itertools.combinations(range(5), 2))
    mean = sum(2.5 * float(ref[list(p)].sum()) for p in pairs) / len(pairs)
    assert mean == pytest.approx(float(ref.sum()), rel=1e-12, abs=0)


def test_subsets_evaluate_the_full_objective_and_return_its_best():
    y = simulate(0.8, 0.5, 0.3, 3, 120, seed=2)
    model = ar1()
    fit = fit_likelihood(
        model, y, x0=X0, P0=P0,
        windows=WindowOptions(window=30, burn_in=5, per_iteration=3, full_every=4),
        iterations=30, optimizer=OptimizerOptions(lr=0.05),
        stopping=StoppingOptions(rtol=0.0, atol=0.0),
    )  # fmt: skip
    assert window_data(y, None, [120] * 3, 30, 5).y.shape[0] > 3
    full = [h for h in fit.history if "objective" in h]
    assert [h["iteration"] for h in full] == [4, 8, 12, 16, 20, 24, 28, 30]
    # the returned parameters: those of the best full objective seen (or the last), scored
    # again with their own window starts for the report
    best = min(full, key=lambda h: h["objective"])
    assert fit.best_iteration in (best["iteration"], 30)
    assert -fit.per_measurement == pytest.approx(best["objective"], abs=1e-3)
    assert fit.log_likelihood > fit.initial_log_likelihood


def test_resumed_fit_on_subsets_equals_uninterrupted(tmp_path):
    y = simulate(0.8, 0.5, 0.3, 3, 120, seed=3)
    windows = WindowOptions(
        window=30, burn_in=5, per_iteration=3, full_every=4, seed=5, refresh_every=4
    )
    kw = dict(x0=X0, P0=P0, windows=windows, iterations=14, optimizer=OptimizerOptions(lr=0.05))
    kw.update(stopping=StoppingOptions(rtol=0.0, atol=0.0))
    m1 = ar1()
    full = fit_likelihood(m1, y, checkpoint=CheckpointOptions(tmp_path / "u.ckpt", every=3), **kw)

    class Killed(Exception):
        pass

    def kill(s):
        if s.iteration == 8:  # after the checkpoint at 6: iterations 7 and 8 are lost
            raise Killed

    ck = tmp_path / "fit.ckpt"
    with pytest.raises(Killed):
        fit_likelihood(ar1(), y, checkpoint=CheckpointOptions(ck, every=3), callback=kill, **kw)
    m3 = ar1()
    resumed = fit_likelihood(m3, y, checkpoint=CheckpointOptions(ck, every=3, resume=True), **kw)
    assert all(torch.equal(a, b) for a, b in zip(state(m3), state(m1), strict=True))

    def strip(history):
        return [{k: v for k, v in h.items() if k != "elapsed"} for h in history]

    assert strip(resumed.history) == strip(full.history)
    assert any("objective" in h for h in full.history)
    assert resumed.log_likelihood == full.log_likelihood


def test_lbfgs_refuses_subsets():
    y = simulate(0.8, 0.5, 0.3, 3, 40, seed=0)
    with pytest.raises(InputError, match="per_iteration"):
        fit_likelihood(
            ar1(), y, x0=X0, P0=P0, optimizer="lbfgs", windows=WindowOptions(per_iteration=2)
        )


def test_calibrate_on_subsets_and_lbfgs_on_all_windows():
    """calibrate's default subsets act with Adam on many windows; with L-BFGS its default is
    every window (no error), an explicit subset is refused."""
    y = simulate(0.8, 0.5, 0.3, 6, 200, seed=4)
    model = ar1(a=0.8)
    default = DEFAULTS["calibrate"].windows.per_iteration
    kw = dict(x0=X0, P0=P0, iterations=6)
    res = calibrate(
        model, Sequences(y), windows=WindowOptions(window=20, burn_in=5, per_iteration=default),
        **kw,
    )  # fmt: skip
    assert res.fit.windows > default
    assert any("objective" in h for h in res.fit.history)
    res = calibrate(
        model, Sequences(y), optimizer="lbfgs",
        windows=WindowOptions(window=20, burn_in=5, per_iteration=default), **kw,
    )  # fmt: skip
    assert not any("objective" in h for h in res.fit.history)
    with pytest.raises(InputError, match="per_iteration"):
        calibrate(
            model, Sequences(y), optimizer="lbfgs",
            windows=WindowOptions(window=20, burn_in=5, per_iteration=4), **kw,
        )  # fmt: skip


def test_recipe_calibrate_keys(tmp_path):
    from torchfilt.pipeline import load_recipe

    base = (
        '[dataset]\npath = "d"\n[transition]\nmodel = "system:reaction"\n'
        '[measurement]\nmodel = "system:reaction"\n'
    )
    p = tmp_path / "r.toml"
    p.write_text(base)
    c = load_recipe(p).calibrate
    assert c["atol"] == 0.01 and c["per_iteration"] == 64
    p.write_text(base + "[calibrate]\natol = 0.5\nper_iteration = 4\n")
    c = load_recipe(p).calibrate
    assert c["atol"] == 0.5 and c["per_iteration"] == 4
    for bad in ("atol = -1", "per_iteration = 0"):
        p.write_text(base + f"[calibrate]\n{bad}\n")
        with pytest.raises(RecipeError, match=bad.split()[0]):
            load_recipe(p)


def test_per_iteration_auto_is_the_fits_default():
    """``WindowOptions(window=...)`` leaves ``per_iteration="auto"``: calibrate's subsets of 64,
    every window for fit_likelihood; an explicit None is every window for calibrate too."""
    from torchfilt.optim import resolve_options

    w = WindowOptions(window=20, burn_in=5)
    assert w.per_iteration == "auto"
    assert resolve_options("calibrate", windows=w).windows.per_iteration == 64
    assert resolve_options("likelihood", windows=w).windows.per_iteration is None
    assert resolve_options("likelihood").windows.per_iteration is None
    all_windows = WindowOptions(window=20, burn_in=5, per_iteration=None)
    assert resolve_options("calibrate", windows=all_windows).windows.per_iteration is None
    y = simulate(0.8, 0.5, 0.3, 6, 200, seed=4)
    res = calibrate(ar1(a=0.8), Sequences(y), x0=X0, P0=P0, iterations=6, windows=w)
    assert res.fit.windows > 64 and any("objective" in h for h in res.fit.history)
    with pytest.raises(InputError, match="per_iteration"):
        WindowOptions(per_iteration="some")  # type: ignore[arg-type]
