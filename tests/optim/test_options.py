"""The fits' typed options (issue 23, "one house"): one spelling per idea, ``None`` meaning the
fit's default, ``patience`` given only when the caller set it, and the flat keywords of before
still working for one release: each family warns, naming its new spelling, and gives the result
of the new spelling bit for bit."""

from __future__ import annotations

import inspect
import math
import warnings
from typing import Any

import pytest
import torch
from torch import nn

import torchfilt
from torchfilt.exceptions import ConvergenceWarning, InputError, InputTypeError
from torchfilt.models import LinearGaussianModel
from torchfilt.models.params import ScalarCovariance
from torchfilt.optim import (
    DEFAULTS,
    CheckpointOptions,
    FitHooks,
    OptimizerOptions,
    StoppingOptions,
    WindowOptions,
    resolve_options,
)
from torchfilt.training import Sequences, calibrate, fit_em, fit_likelihood, fit_measurement_only

DT = torch.float64
X0, P0 = torch.zeros(1, dtype=DT), torch.eye(1, dtype=DT)


def simulate(T: int, seed: int, batch: int = 1) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    x, ys = torch.zeros(batch, 1, dtype=DT), []
    for _ in range(T):
        x = 0.9 * x + 0.5 * torch.randn(batch, 1, generator=g, dtype=DT)
        ys.append(x + 0.7 * torch.randn(batch, 1, generator=g, dtype=DT))
    return torch.stack(ys, -2)


class Gain(nn.Module):
    def __init__(self) -> None:
        super().__init__()
        self.A = nn.Parameter(torch.tensor([[0.5]], dtype=DT))

    def forward(self, x: torch.Tensor, u: torch.Tensor | None = None) -> torch.Tensor:
        return x @ self.A.mT


def ar1() -> torchfilt.StateSpaceModel:
    return torchfilt.StateSpaceModel(
        Gain(),
        lambda x, u: x,
        Q=ScalarCovariance(1.0, 1, dtype=DT),
        R=ScalarCovariance(1.0, 1, dtype=DT),
    )


def values(model: nn.Module) -> torch.Tensor:
    return torch.cat([p.detach().reshape(-1) for p in model.parameters()])


def same_fit(old: Any, new: Any) -> None:
    assert old.iterations == new.iterations and old.stopped == new.stopped
    assert [h["loss"] for h in old.history] == [h["loss"] for h in new.history]
    assert old.log_likelihood == new.log_likelihood


def likelihood(y: torch.Tensor, **kw: Any) -> tuple[Any, torch.Tensor]:
    model = ar1()
    fit = fit_likelihood(model, y, x0=X0, P0=P0, iterations=kw.pop("iterations", 6), **kw)
    return fit, values(model)


def old_and_new(old: dict[str, Any], new: dict[str, Any], match: str, **common: Any) -> None:
    """The fit with the deprecated keywords ``old`` warns (``match``) and equals the fit with
    ``new`` bit for bit."""
    y = simulate(60, seed=2, batch=3)
    with pytest.warns(DeprecationWarning, match=match):
        a, va = likelihood(y, **old, **common)
    b, vb = likelihood(y, **new, **common)
    same_fit(a, b)
    assert torch.equal(va, vb)


# --------------------------------------------------------------------- one family per test
def test_params_is_parameters():
    def model_and_params() -> tuple[torchfilt.StateSpaceModel, list[nn.Parameter]]:
        m = ar1()
        return m, [m.transition._fn.A]

    y = simulate(50, seed=1)
    m1, p1 = model_and_params()
    with pytest.warns(DeprecationWarning, match=r"params= is deprecated; pass parameters="):
        a = fit_likelihood(m1, y, x0=X0, P0=P0, iterations=5, params=p1)
    m2, p2 = model_and_params()
    b = fit_likelihood(m2, y, x0=X0, P0=P0, iterations=5, parameters=p2)
    same_fit(a, b)
    assert torch.equal(values(m1), values(m2))
    assert float(m1.transition.noise_cov().detach().reshape(())) == 1.0  # Q was not fitted


def test_lr_is_an_optimizer_field():
    old_and_new(  # one L-BFGS iteration (up to 20 inner steps) shows the lr it was given
        {"optimizer": "lbfgs", "lr": 0.3},
        {"optimizer": OptimizerOptions("lbfgs", lr=0.3)},
        r"lr= is deprecated; pass optimizer=OptimizerOptions\(lr=\.\.\.\)",
        iterations=1,
    )


def test_window_keywords_are_window_options():
    old_and_new(
        {"window": 20, "burn_in": 4, "start": "smoothed", "refresh_every": 2},
        {"windows": WindowOptions(window=20, burn_in=4, start="smoothed", refresh_every=2)},
        r"= is deprecated; pass windows=WindowOptions\(",
    )


def test_stopping_keywords_are_stopping_options():
    val = Sequences(simulate(60, seed=9, batch=2))
    old_and_new(
        {"patience": 2, "validate_every": 2, "tol": 1e-6, "rtol": 1e-3, "rtol_window": 3},
        {"stopping": StoppingOptions(2, 2, 1e-6, 1e-3, 3)},
        r"= is deprecated; pass stopping=StoppingOptions\(",
        validation=val,
        iterations=30,
        optimizer=OptimizerOptions(lr=0.2),
    )


def test_checkpoint_keywords_are_checkpoint_options(tmp_path):
    lg = lambda: LinearGaussianModel(  # noqa: E731
        torch.full((1, 1), 0.5, dtype=DT), torch.eye(1, dtype=DT), P0.clone(), P0.clone()
    )
    y = simulate(60, seed=4)
    common = dict(x0=X0, P0=P0, known_channels=[0])
    for name in ("old", "new"):  # two iterations, then resumed to five
        fit_em(lg(), y, iterations=2, checkpoint=tmp_path / f"{name}.ckpt", **common)
    with pytest.warns(
        DeprecationWarning,
        match=r"(resume|checkpoint_every)= is deprecated; pass checkpoint=CheckpointOptions\(",
    ):
        a = fit_em(
            lg(), y, iterations=5, checkpoint=tmp_path / "old.ckpt", checkpoint_every=2,
            resume=True, **common,
        )  # fmt: skip
    b = fit_em(
        lg(), y, iterations=5,
        checkpoint=CheckpointOptions(tmp_path / "new.ckpt", every=2, resume=True), **common,
    )  # fmt: skip
    same_fit(a, b)
    assert [h["iteration"] for h in a.history] == [1, 2, 3, 4, 5]
    assert torch.load(tmp_path / "old.ckpt", weights_only=True)["iteration"] == 5


def test_hooks_keywords_are_fit_hooks():
    seen: dict[str, list[int]] = {"old": [], "new": []}

    def hooks(name: str) -> dict[str, Any]:
        return {"project": lambda: seen[name].append(1), "prepare": lambda: seen[name].append(2)}

    y = simulate(40, seed=3)
    with pytest.warns(
        DeprecationWarning, match=r"(project|prepare)= is deprecated; pass hooks=FitHooks\("
    ):
        a, va = likelihood(y, **hooks("old"))
    b, vb = likelihood(y, hooks=FitHooks(**hooks("new")))
    same_fit(a, b)
    assert torch.equal(va, vb) and seen["old"] == seen["new"] and 1 in seen["new"]


def test_gp_lr_is_an_optimizer_field():
    from torchfilt.models.gp import GPMeasurement

    g = torch.Generator().manual_seed(0)
    x = torch.rand(40, 1, generator=g, dtype=DT)
    y = torch.sin(6 * x) + 0.1 * torch.randn(40, 1, generator=g, dtype=DT)
    a = GPMeasurement.fit(x, y, iterations=0, progress=False)
    b = GPMeasurement.fit(x, y, iterations=0, progress=False)
    with pytest.warns(DeprecationWarning, match=r"lr= is deprecated; pass optimizer="):
        la = a.optimize(5, lr=0.2, progress=False)
    lb = b.optimize(5, optimizer=OptimizerOptions("adam", lr=0.2), progress=False)
    assert la == lb and len(la) == 5


# --------------------------------------------------------------------- the rules
def test_an_old_keyword_with_its_group_is_refused():
    y = simulate(20, seed=0)
    with (
        pytest.warns(DeprecationWarning),
        pytest.raises(InputError, match=r"lr= and optimizer= both given"),
    ):
        fit_likelihood(ar1(), y, x0=X0, P0=P0, lr=0.1, optimizer=OptimizerOptions("adam"))
    with (
        pytest.warns(DeprecationWarning),
        pytest.raises(InputError, match=r"patience=, tol= and stopping= both given"),
    ):
        fit_likelihood(ar1(), y, x0=X0, P0=P0, patience=2, tol=0.0, stopping=StoppingOptions())
    with pytest.warns(DeprecationWarning), pytest.raises(InputError, match="params= and"):
        fit_likelihood(ar1(), y, x0=X0, P0=P0, params=[], parameters=[])


@pytest.mark.parametrize("fit", [fit_likelihood, calibrate, fit_em, fit_measurement_only])
def test_signatures_show_one_spelling_per_idea(fit):
    params = inspect.signature(fit).parameters
    old = {"lr", "tol", "rtol", "rtol_window", "patience", "validate_every", "window", "burn_in"}
    old |= {"start", "refresh_every", "checkpoint_every", "resume", "params", "project"}
    old |= {"prepare", "all_reduce"}
    assert not old & set(params), sorted(old & set(params))
    assert {"iterations", "stopping", "checkpoint", "hooks"} <= set(params)
    assert params["iterations"].default is None and params["stopping"].default is None
    assert all(p.kind is not p.VAR_KEYWORD for p in params.values())
    assert inspect.unwrap(fit) is not fit  # the decorator keeps the signature of the fit


def decorated_fits() -> list[Any]:
    from torchfilt.models.gp import GPMeasurement, GPModel, GPTransition
    from torchfilt.pipeline.distributed import calibrate_ray, fit_measurement_only_ray

    fits = [fit_likelihood, calibrate, fit_em, fit_measurement_only, calibrate_ray]
    fits += [fit_measurement_only_ray, GPModel.optimize, GPTransition.fit, GPMeasurement.fit]
    return fits


@pytest.mark.parametrize("fit", decorated_fits(), ids=lambda f: f.__qualname__)
def test_an_unknown_keyword_is_an_input_error(fit):
    """A misspelt keyword is refused before the fit runs (so no data are needed here), naming
    it, the keyword it resembles and every valid one, instead of Python's ``TypeError``."""
    params = inspect.signature(fit).parameters
    valid = sorted(
        name
        for name, p in params.items()
        if p.kind in (p.POSITIONAL_OR_KEYWORD, p.KEYWORD_ONLY) and name not in ("self", "cls")
    )
    with pytest.raises(InputError) as err:
        fit(None, None, iterationz=3)
    message = str(err.value)
    name = fit.__qualname__
    assert message.startswith(f"{name}: unexpected keyword argument(s) ['iterationz']"), message
    assert "did you mean iterations= for iterationz=?" in message
    assert message.endswith(f"; valid: {valid}")
    with pytest.raises(InputError, match=r"\['zebra', 'shape'\]; valid"):
        fit(None, None, zebra=1, shape=2)  # nothing close: no hint


def test_a_fit_with_var_keywords_is_not_checked():
    """A decorated function that takes ``**`` passes every keyword through (its own business)."""
    from torchfilt.optim import deprecated_fit_keywords

    @deprecated_fit_keywords("likelihood")
    def fit(y: Any, *, optimizer: Any = None, **rest: Any) -> dict[str, Any]:
        return {"optimizer": optimizer, **rest}

    assert fit(0, anything=1) == {"optimizer": None, "anything": 1}
    with pytest.warns(DeprecationWarning, match="lr= is deprecated"):
        assert fit(0, lr=0.5)["optimizer"] == OptimizerOptions(lr=0.5)


def test_none_is_the_fits_default_and_strings_are_shortcuts():
    o = resolve_options("calibrate")
    assert o.iterations == DEFAULTS["calibrate"].iterations == 100
    assert o.optimizer.lr == 0.1 and o.windows.window == 100 and o.stopping.patience == 15
    assert not o.patience_given and o.checkpoint.every == 10
    lb = resolve_options("calibrate", optimizer="lbfgs", checkpoint="c.ckpt")
    # the fit's learning rate, as calibrate(optimizer="lbfgs") has always used
    assert lb.optimizer == OptimizerOptions("lbfgs", lr=0.1)
    assert lb.checkpoint == CheckpointOptions("c.ckpt", every=10)
    em = resolve_options("em", stopping=StoppingOptions(rtol=0.0), checkpoint="e.ckpt")
    assert em.stopping.tol == 1e-9 and em.stopping.rtol == 0.0 and em.checkpoint.every == 1
    with pytest.raises(InputError, match="iterations must be at least 1"):
        resolve_options("likelihood", iterations=0)
    with pytest.raises(InputTypeError, match="stopping: expected StoppingOptions"):
        resolve_options("likelihood", stopping={"patience": 3})  # type: ignore[arg-type]
    with pytest.raises(InputError, match="resume=True needs checkpoint="):
        CheckpointOptions(resume=True)


def test_patience_counts_as_given_when_the_caller_set_it():
    """Even at the default value: ``StoppingOptions(patience=20)`` without held-out data warns
    (the old inference compared with the default and missed it); the default does not."""
    y = simulate(30, seed=5)
    assert resolve_options("likelihood", stopping=StoppingOptions(patience=20)).patience_given
    with pytest.warns(ConvergenceWarning, match="patience=20 was given but there is no held-out"):
        fit_likelihood(ar1(), y, x0=X0, P0=P0, iterations=2, stopping=StoppingOptions(patience=20))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        fit_likelihood(ar1(), y, x0=X0, P0=P0, iterations=2, stopping=StoppingOptions(rtol=0))
        calibrate(
            ar1(), Sequences(y), x0=X0, P0=P0, iterations=2, windows=WindowOptions(window=None)
        )


def test_calibrate_default_budget_is_the_recipes():
    """One default per fit: ``calibrate`` runs 100 iterations, as ``torchfilt train`` always did
    (``DEFAULTS["calibrate"]`` said 150 before)."""
    y = simulate(30, seed=6)
    fit = calibrate(
        ar1(), Sequences(y), x0=X0, P0=P0, windows=WindowOptions(window=None),
        stopping=StoppingOptions(rtol=0.0, atol=0.0),
    ).fit  # fmt: skip
    assert fit.iterations == 100 and math.isfinite(fit.log_likelihood)


def test_the_table_of_the_options_module_is_true():
    """The table of where the fits' defaults differ (``torchfilt.optim.options``) says what
    ``DEFAULTS`` holds."""
    import torchfilt.optim.options as module

    doc = module.__doc__ or ""
    rows = doc.split("================  =========")[2].strip().splitlines()[1:]
    table = {row.split()[0]: row.split() for row in rows if row.strip() and "=" not in row}
    assert set(table) == set(DEFAULTS)

    def shown(v: object) -> str:
        return "auto" if v is None else f"{v:g}" if isinstance(v, float) else str(v)

    for fit in ("likelihood", "calibrate", "measurement_only"):
        d = DEFAULTS[fit]
        _, opt, lr, its, window, burn_in, patience, every = table[fit]
        assert opt == d.optimizer.optimizer and lr == shown(d.optimizer.lr), fit
        assert int(its) == d.iterations and window == str(d.windows.window), fit
        assert int(burn_in) == d.windows.burn_in and int(patience) == d.stopping.patience, fit
        assert int(every) == d.checkpoint.every, fit
    em, gp = table["em"], table["gp"]
    assert int(next(t for t in em if t.isdigit())) == DEFAULTS["em"].iterations
    assert int(em[-1]) == DEFAULTS["em"].checkpoint.every
    assert (
        gp[1] == DEFAULTS["gp"].optimizer.optimizer and float(gp[2]) == DEFAULTS["gp"].optimizer.lr
    )
    assert int(gp[3]) == DEFAULTS["gp"].iterations


@pytest.mark.parametrize("name", ["calibrate_ray", "fit_measurement_only_ray"])
def test_ray_fits_name_their_data_y_and_warn_for_recordings(name: str, monkeypatch) -> None:
    """The Ray fits name their data ``y`` like every fit; ``recordings=``, their old name, is
    folded into ``y`` with a ``DeprecationWarning`` (the group itself is stubbed: no Ray)."""
    from torchfilt.pipeline.distributed import fits

    seen: list[Any] = []
    monkeypatch.setattr(fits, "_run_group", lambda *args: seen.append(args[3]) or "ran")
    fn = getattr(fits, name)
    assert list(inspect.signature(fn).parameters)[:2] == ["model", "y"]
    data = [torch.zeros(3, 1, dtype=torch.float64)]
    kw: dict[str, Any] = dict(x0=torch.zeros(1), P0=torch.eye(1))
    if name == "fit_measurement_only_ray":
        kw["known_channels"] = [0]
    with pytest.warns(DeprecationWarning, match="recordings= is deprecated; pass y="):
        assert fn(None, recordings=data, **kw) == "ran"
    assert seen == [data]
