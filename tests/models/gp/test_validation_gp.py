"""GP fit input validation (issue 12): huge values, integer dtypes, bad learning rates,
recordings of different dimensions."""

from __future__ import annotations

import math

import pytest
import torch
from gp_support import DT, one_thread, smooth_data

from torchfilt.exceptions import InputError, ShapeError
from torchfilt.models.gp import GPMeasurement, GPTransition
from torchfilt.models.gp.data import max_magnitude
from torchfilt.optim import OptimizerOptions

__all__ = ["one_thread"]

#: a few Adam steps: these tests check validation, not the fit
ITERS = 3


@pytest.mark.parametrize("scale", [1e154, 1e200, 1e300])
def test_huge_targets_are_refused(scale, one_thread):
    """Before: |y| >= 1e154 overflowed the standard deviation and the model predicted NaN."""
    x, y = smooth_data(20)
    with pytest.raises(InputError, match=r"y: values up to .* rescale the data"):
        GPMeasurement.fit(x, scale * y, iterations=ITERS, progress=False)
    with pytest.raises(InputError, match=r"x: values up to"):
        GPTransition.fit(scale * x, None, x, iterations=ITERS, progress=False)


def test_large_but_representable_targets_fit_finitely(one_thread):
    """Just below the limit the standardised model predicts finite values on the data's scale."""
    x, y = smooth_data(20)
    scale = 1e140
    assert scale * float(y.abs().max()) < max_magnitude(DT)
    h = GPMeasurement.fit(x, scale * y, iterations=ITERS, progress=False)
    pred = h.predict(x[:4])
    assert torch.isfinite(pred.mean).all() and torch.isfinite(pred.var).all()
    assert bool((pred.var > 0).all())
    # the mean is on the data's scale: relative error of a smooth fit, far below 1
    rel = (pred.mean - scale * y[:4]).abs().max() / (scale * y.abs().max())
    assert float(rel) < 0.5


def test_limit_follows_the_dtype():
    assert max_magnitude(torch.float64) == pytest.approx(math.sqrt(torch.finfo(DT).max) / 1e4)
    assert max_magnitude(torch.float32) < 1e16


@pytest.mark.parametrize("dtype", [torch.int64, torch.int32, torch.float16, torch.bfloat16])
def test_non_float_training_dtype_is_refused(dtype, one_thread):
    """Before: dtype=torch.int64 truncated the data to integers."""
    x, y = smooth_data(20)
    with pytest.raises(InputError, match=rf"dtype: .*got {dtype}"):
        GPMeasurement.fit(x, y, dtype=dtype, iterations=ITERS, progress=False)
    with pytest.raises(InputError, match=rf"dtype: .*got {dtype}"):
        GPTransition.fit(x, None, x, dtype=dtype, iterations=ITERS, progress=False)


def test_half_precision_data_is_refused(one_thread):
    x, y = smooth_data(20)
    with pytest.raises(InputError, match=r"y: torch\.float16 is not supported"):
        GPMeasurement.fit(x, y.half(), iterations=ITERS, progress=False)


@pytest.mark.parametrize("lr", [float("nan"), float("inf"), 1e6, 5.0, 0.0, -0.1, "0.1"])
def test_bad_learning_rate_is_refused(lr, one_thread):
    x, y = smooth_data(20)
    # OptimizerOptions refuses what no optimiser takes; the GP fit what is above its own bound
    with pytest.raises(InputError, match=r"lr must be a (finite positive )?number"):
        adam = OptimizerOptions("adam", lr=lr)
        GPMeasurement.fit(x, y, optimizer=adam, iterations=ITERS, progress=False)
    with pytest.raises(InputError, match=r"natural_lr must be a number"):
        GPTransition.fit(x, None, x, natural_lr=lr, iterations=ITERS, progress=False)


def test_bad_iterations_are_refused(one_thread):
    x, y = smooth_data(20)
    for bad in (-1, 2.5, True):
        with pytest.raises(InputError, match="iterations must be a non-negative integer"):
            GPMeasurement.fit(x, y, iterations=bad, progress=False)


def test_unknown_option_is_an_input_error(one_thread):
    x, y = smooth_data(20)
    with pytest.raises(InputError, match=r"unexpected keyword argument\(s\) \['iterationz'\]"):
        GPMeasurement.fit(x, y, iterationz=3)


def test_recordings_of_different_state_dimensions(one_thread):
    g = torch.Generator().manual_seed(0)
    a = torch.randn(12, 2, generator=g, dtype=DT)
    b = torch.randn(12, 3, generator=g, dtype=DT)
    ya, yb = a[:, :1], b[:, :1]
    with pytest.raises(ShapeError, match=r"x\[1\]: 3 columns, expected 2 like x\[0\]"):
        GPMeasurement.fit([a, b], [ya, yb], iterations=ITERS, progress=False)
    with pytest.raises(ShapeError, match=r"y\[1\]: 2 columns, expected 1 like y\[0\]"):
        GPMeasurement.fit([a, a], [ya, a], iterations=ITERS, progress=False)
    with pytest.raises(ShapeError, match=r"u\[1\]: 2 columns, expected 1 like u\[0\]"):
        GPMeasurement.fit([a, a], [ya, ya], [ya, a], iterations=ITERS, progress=False)
    with pytest.raises(ShapeError, match=r"x\[1\]: 3 state components, expected 2"):
        GPTransition.fit([a, b], iterations=ITERS, progress=False)
    with pytest.raises(ShapeError, match=r"u\[1\]: 2 columns, expected 1 like u\[0\]"):
        GPTransition.fit([a, a], [ya[:-1], a[:-1]], iterations=ITERS, progress=False)


@pytest.mark.parametrize("dtype", [torch.float16, torch.int64])
def test_predict_applies_the_dtype_rule(dtype, one_thread):
    x, y = smooth_data(20)
    h = GPMeasurement.fit(x, y, iterations=ITERS, progress=False)
    with pytest.raises(InputError, match="x: "):
        h.predict(x[:3].to(dtype))
