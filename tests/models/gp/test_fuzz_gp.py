"""Hypothesis suite over the GP models on tiny data (issue 12): GPMeasurement / GPTransition fit and
predict with random sizes, scales, missing targets and options, good and bad. Each case is refused
with a TorchfiltError or gives a model whose predictions are finite with positive variances, and
interpolate a noise-free constant target exactly. See tests/fuzz_support.py for the contract."""

from __future__ import annotations

from typing import Any

import numpy as np
import torch
from fuzz_support import Refused, attempt, print_stats, property_tests
from hypothesis import strategies as st

from torchfilt.models.gp import GPMeasurement, GPTransition
from torchfilt.optim import OptimizerOptions

D = torch.float64
#: a constant target is reproduced to round-off relative to its size
CONST_RTOL = 1e-9


def check_gp(data: st.DataObject) -> None:
    old = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        _check_gp(data)
    finally:
        torch.set_num_threads(old)


def at_rate(fit: Any) -> Any:
    """``fit`` taking the Adam learning rate ``lr=`` (an invalid one is refused, by
    ``OptimizerOptions`` or by the GP fit, inside the attempt)."""

    def call(*args: Any, lr: float, **kwargs: Any) -> Any:
        return fit(*args, optimizer=OptimizerOptions("adam", lr=lr), **kwargs)

    return call


_FAULTS = [None] * 8 + ["lr", "dtype", "huge x", "huge y", "inf", "few points", "missing"]


def _check_gp(data: st.DataObject) -> None:
    role = data.draw(st.sampled_from(["measurement", "transition"]), label="role")
    fault = data.draw(st.sampled_from(_FAULTS), label="fault")
    N = 3 if fault == "few points" else data.draw(st.integers(5, 14), label="N")
    n = data.draw(st.integers(1, 2), label="n")
    m = data.draw(st.integers(1, 2), label="m") if role == "measurement" else n
    rng = np.random.default_rng(data.draw(st.integers(0, 2**32 - 1), label="seed"))
    xscale = 10.0 ** (160 if fault == "huge x" else data.draw(st.sampled_from([-3, 0, 3])))
    yscale = 10.0 ** (
        data.draw(st.sampled_from([155, 200]))
        if fault == "huge y"
        else data.draw(st.sampled_from([-3, 0, 3]))
    )
    x = rng.standard_normal((N, n)) * xscale
    target = data.draw(st.sampled_from(["smooth", "smooth", "constant"]), label="target")
    y = np.sin(x[:, :1] / xscale + np.arange(m)) * yscale
    if target == "constant":
        y = np.full((N, m), 0.7 * yscale)
    if fault == "missing":  # allowed for a measurement (dropped per output), not a transition
        y[rng.uniform(size=y.shape) < 0.2] = np.nan
        y[1, 0] = np.nan
    elif fault == "inf":
        y[0, 0] = np.inf
    lr = data.draw(st.sampled_from([0.05, 0.5]))
    if fault == "lr":
        lr = data.draw(st.sampled_from([float("nan"), float("inf"), 1e6, 0.0, -1.0]))
    dtype = data.draw(st.sampled_from([D, D, torch.float32]))
    if fault == "dtype":
        dtype = data.draw(st.sampled_from([torch.int64, torch.int32, torch.float16]))
    opts: dict = dict(
        iterations=data.draw(st.integers(0, 3), label="iterations"),
        lr=lr,
        kernel=data.draw(st.sampled_from(["rbf", "matern52", "matern12"]), label="kernel"),
        dtype=dtype,
        progress=False,
    )
    xt, yt = torch.tensor(x, dtype=D), torch.tensor(y, dtype=D)
    if role == "measurement":
        model, _ = attempt("GPMeasurement.fit", at_rate(GPMeasurement.fit), xt, yt, **opts)
    else:
        xn = xt + 0.1 * yt[:, :n] / yscale * xscale
        if fault in ("missing", "inf", "huge y"):
            xn = yt[:, :n]
        model, _ = attempt("GPTransition.fit", at_rate(GPTransition.fit), xt, None, xn, **opts)
    if isinstance(model, Refused):
        # a clean problem is never refused (a missing measurement is allowed when each output
        # keeps enough observed rows)
        assert fault is not None, model
        return
    allowed = (None, "missing") if role == "measurement" else (None,)
    assert fault in allowed, f"{role}: fault {fault!r} accepted"
    q = torch.tensor(rng.standard_normal((5, n)) * xscale, dtype=opts["dtype"])
    pred, _ = attempt(f"{type(model).__name__}.predict", model.predict, q)
    assert not isinstance(pred, Refused), pred
    assert torch.isfinite(pred.mean).all(), "non-finite predictive mean"
    assert torch.isfinite(pred.var).all() and bool((pred.var >= 0).all()), "bad variance"
    if target != "constant":
        # only an output without spread in the data is predicted with zero variance (by design:
        # the standardiser marks it constant)
        assert bool((pred.var > 0).all()), "zero variance for a varying output"
    if target == "constant" and role == "measurement":
        want = torch.full_like(pred.mean, 0.7 * yscale)
        assert torch.allclose(
            pred.mean,
            want,
            rtol=CONST_RTOL * 1e4 if q.dtype == torch.float32 else CONST_RTOL,
            atol=0,
        )


test_fuzz_gp, test_fuzz_gp_long = property_tests(check_gp, short=3, long=500)


def teardown_module() -> None:
    print_stats()
