"""Hypothesis suite over the fits' argument checks (issue 24, item 10): ``fit_likelihood``,
``calibrate``, ``fit_em`` and ``fit_measurement_only`` (either method) with tiny budgets, valid or with one argument corrupted (half
precision or integer data, a recording without steps, inputs for a model without any, a prior of
the wrong shape or indefinite, a bad budget, learning rate, dtype, ``fixed`` name or
``compile`` mode).

A corrupted case must be refused with a TorchfiltError that names the corrupted argument; a
valid one must return a finite fit whose log-likelihood is at least the initial one (the fits
return their best iterate). See tests/fuzz_support.py for the contract and the counts.
"""

from __future__ import annotations

import math

import numpy as np
import torch
from fuzz_support import Refused, attempt, print_stats, property_tests
from hypothesis import strategies as st

from torchfilt import LinearGaussianModel, calibrate, fit_em, fit_likelihood, fit_measurement_only
from torchfilt.models.params import ScalarCovariance
from torchfilt.optim import OptimizerOptions, WindowOptions
from torchfilt.training.likelihood import Sequences

D = torch.float64

#: the corruption of a case, and the argument its refusal must name
CORRUPTIONS = {
    "none": None,
    "y float16": "y",
    "y int64": "y",
    "y no steps": "y",
    "u without inputs": "u",
    "x0 wrong shape": "x0",
    "P0 indefinite": "P0",
    "iterations negative": "iterations",
    "iterations bool": "iterations",
    "lr negative": "lr",
    "dtype int": "dtype",
    "fixed unknown": "fixed",
    "accelerate not a bool": "accelerate",
    "compile not a mode": "compile",
    "noise_scale unknown": "noise_scale",
    "holdout out of range": "holdout",
}
FITS = ["fit_likelihood", "calibrate", "fit_em", "fit_measurement_only"]


def _model(n: int, rng: np.random.Generator) -> LinearGaussianModel:
    A = np.eye(n) * 0.9 + rng.uniform(-0.05, 0.05, (n, n))
    H = np.zeros((1, n))
    H[0, 0] = 1.0
    t = lambda a: torch.tensor(a, dtype=D)  # noqa: E731
    # a learnable Q: fit_likelihood has a parameter to fit
    return LinearGaussianModel(t(A), t(H), ScalarCovariance(0.1, n, dtype=D), t(np.eye(1)))


def _call(fit: str, model, y, u, x0, P0, options: dict):
    options = dict(options)
    # the option groups are built inside the attempt: a bad value is refused by the public API
    if "lr" in options:
        options["optimizer"] = OptimizerOptions(lr=options.pop("lr"))
    if "burn_in" in options:
        options["windows"] = WindowOptions(burn_in=options.pop("burn_in"))
    if fit == "fit_likelihood":
        return fit_likelihood(model, y, u, x0=x0, P0=P0, **options)
    if fit == "fit_em":
        return fit_em(model, y, u, x0=x0, P0=P0, known_channels=[0], **options)
    if fit == "fit_measurement_only":
        return fit_measurement_only(model, y, u, x0=x0, P0=P0, known_channels=[0], **options)
    return calibrate(model, Sequences(y, u), x0=x0, P0=P0, **options)


def check_fits(data: st.DataObject) -> None:
    fit = data.draw(st.sampled_from(FITS), label="fit")
    n = data.draw(st.integers(1, 2), label="n")
    R, T = data.draw(st.integers(1, 3), label="recordings"), data.draw(st.integers(3, 12), "T")
    rng = np.random.default_rng(data.draw(st.integers(0, 2**32 - 1), label="seed"))
    # valid cases a third of the time
    kinds = sorted(CORRUPTIONS) + ["none"] * (len(CORRUPTIONS) // 2)
    corruption = data.draw(st.sampled_from(kinds), label="corruption")
    what = CORRUPTIONS[corruption]
    model = _model(n, rng)
    y = torch.tensor(rng.standard_normal((R, T, 1)), dtype=D)
    u = None
    x0, P0 = torch.zeros(n, dtype=D), torch.eye(n, dtype=D)
    options: dict = {"iterations": data.draw(st.integers(1, 2), label="iterations")}
    em = fit == "fit_em"
    if fit == "fit_measurement_only":
        options["method"] = data.draw(
            st.sampled_from(["em", "likelihood", "auto", "both"]), "method"
        )
        em = options["method"] == "em"
        scale = data.draw(st.sampled_from(["auto", "none", "held-out"]), label="noise scale")
        if scale == "held-out":
            # half of each recording (T >= 3): every one keeps 2 steps and holds out 1
            options.update(noise_scale="held-out", holdout=0.5)
        elif scale == "none":
            options["noise_scale"] = "none"
    if not em:
        options.update(lr=0.05, burn_in=0)
    elif fit == "fit_em":  # plain or SQUAREM-accelerated EM (None: the default, on here)
        options["accelerate"] = data.draw(st.sampled_from([None, True, False]), "accelerate")
    if corruption == "y float16":
        y = y.half()
    elif corruption == "y int64":
        y = y.to(torch.int64)
    elif corruption == "y no steps":
        y = y[:, :0]
    elif corruption == "u without inputs":
        u = torch.ones(R, T, data.draw(st.integers(1, 2), label="u width"), dtype=D)
    elif corruption == "x0 wrong shape":
        x0 = torch.zeros(n + 1, dtype=D)
    elif corruption == "P0 indefinite":
        P0 = -P0
    elif corruption == "iterations negative":
        options["iterations"] = -1
    elif corruption == "iterations bool":
        options["iterations"] = True
    elif corruption == "lr negative":
        if em:
            corruption, what = "none", None  # EM has no learning rate
        else:
            options["lr"] = -0.1
    elif corruption == "dtype int":
        options["dtype"] = torch.int64
    elif corruption == "fixed unknown":
        options["fixed"] = ("no_such_parameter",)
    elif corruption == "accelerate not a bool":
        if fit == "fit_em":
            options["accelerate"] = "yes"
        else:
            corruption, what = "none", None  # only fit_em accelerates
    elif corruption == "compile not a mode":
        if fit in ("fit_em", "fit_measurement_only"):  # False, True, "step" or "loop"
            options["compile"] = data.draw(st.sampled_from(["fast", 1, None]), label="compile")
        else:
            corruption, what = "none", None
    elif corruption == "noise_scale unknown":
        if fit == "fit_measurement_only":
            options["noise_scale"] = data.draw(st.sampled_from(["Auto", 1.0, None]), "scale")
        else:
            corruption, what = "none", None
    elif corruption == "holdout out of range":
        if fit == "fit_measurement_only":
            options.update(noise_scale="held-out")
            options["holdout"] = data.draw(st.sampled_from([0.0, 1.0, 1.5, -0.2]), "holdout")
        else:
            corruption, what = "none", None
    res, _ = attempt(fit, _call, fit, model, y, u, x0, P0, options)
    if what is not None:
        assert isinstance(res, Refused), f"{fit}, {corruption}: not refused"
        message = str(res.error)
        assert what in message, f"{fit}, {corruption}: the refusal does not name {what}: {message}"
        return
    assert not isinstance(res, Refused), f"{fit}: a valid problem was refused: {res}"
    result = res.fit if fit == "calibrate" else res
    ll, ll0 = float(result.log_likelihood), float(result.initial_log_likelihood)
    assert math.isfinite(ll) and math.isfinite(ll0), (ll, ll0)
    assert ll >= ll0 - 1e-9 * abs(ll0), f"{fit}: returned {ll} below the initial {ll0}"
    if options.get("noise_scale") == "held-out":
        assert result.noise_scale is not None and result.noise_scale.held_out >= R


test_fuzz_fits, test_fuzz_fits_long = property_tests(check_fits, short=12, long=300)


def teardown_module() -> None:
    print_stats()
