"""The GP fits' options are explicit keyword arguments (issue 23): both fits state the one list
of :func:`~torchfilt.models.gp.fitting.fit_model` (``GPMeasurement.fit`` all but
``increment``), with the same types and defaults, each default the one of the method it feeds
(``_from_pairs``, ``optimize``, ``freeze``); ``lr=`` of before is ``optimizer=`` bit for bit,
with a ``DeprecationWarning``."""

from __future__ import annotations

import inspect

import pytest
import torch

from torchfilt.exceptions import InputError
from torchfilt.models.gp import GPMeasurement, GPModel, GPTransition
from torchfilt.models.gp.fitting import FIT_KEYWORDS, fit_model
from torchfilt.optim import OptimizerOptions

DT = torch.float64
#: The keywords a fit has beyond fit_model's: the dtype its data are prepared in.
DATA_KEYWORDS = {"dtype"}


def keyword_only(func: object) -> dict[str, inspect.Parameter]:
    params = inspect.signature(func).parameters.values()  # type: ignore[arg-type]
    return {p.name: p for p in params if p.kind is p.KEYWORD_ONLY}


def test_the_fits_state_the_one_list_of_options():
    assert set(keyword_only(GPTransition.fit)) == set(FIT_KEYWORDS) | DATA_KEYWORDS
    assert set(keyword_only(GPMeasurement.fit)) == set(FIT_KEYWORDS) - {"increment"} | DATA_KEYWORDS
    for fit in (GPTransition.fit, GPMeasurement.fit):
        assert all(p.kind is not p.VAR_KEYWORD for p in inspect.signature(fit).parameters.values())


def test_both_fits_have_the_same_types_and_defaults():
    t, m = keyword_only(GPTransition.fit), keyword_only(GPMeasurement.fit)
    shared = keyword_only(fit_model)
    for name, p in m.items():
        assert (p.annotation, p.default) == (t[name].annotation, t[name].default), name
        if name in shared:
            assert p.annotation == shared[name].annotation, name


def test_each_default_is_the_one_of_the_method_it_feeds():
    fed = {}
    for method in (GPModel._from_pairs, GPModel.optimize, GPModel.freeze):
        fed.update(inspect.signature(method).parameters)
    t = keyword_only(GPTransition.fit)
    for name, p in t.items():
        if name in fed:
            assert p.default == fed[name].default, name
    assert set(t) - set(fed) == {"dtype", "device"}
    assert t["dtype"].default is DT and t["device"].default is None


def test_the_options_reach_the_model():
    g = torch.Generator().manual_seed(0)
    x = torch.rand(30, 2, generator=g, dtype=DT)
    y = torch.sin(4 * x[:, :1]) + 0.05 * torch.randn(30, 1, generator=g, dtype=DT)
    h = GPMeasurement.fit(
        x, y, kernel="matern32", inputs=[0], iterations=3, variance="exact", chunk_size=7,
        progress=False,
    )  # fmt: skip
    assert h.config.kernel == "matern32" and h.config.groups[0].features == (0,)
    assert len(h.history) == 3 and h.freeze_options == {
        "variance": "exact", "rank": None, "tol": 0.05, "chunk_size": 7,
    }  # fmt: skip


def test_lr_is_the_optimizers_field_bit_for_bit():
    g = torch.Generator().manual_seed(1)
    x = torch.randn(3, 21, 2, generator=g, dtype=DT).cumsum(-2) * 0.1
    with pytest.warns(DeprecationWarning, match=r"GPTransition\.fit: lr= is deprecated"):
        a = GPTransition.fit(x, increment=True, iterations=5, lr=0.2, progress=False)
    b = GPTransition.fit(
        x, increment=True, iterations=5, optimizer=OptimizerOptions("adam", lr=0.2),
        progress=False,
    )  # fmt: skip
    assert a.history == b.history
    with pytest.warns(DeprecationWarning), pytest.raises(InputError, match="lr= and optimizer="):
        GPTransition.fit(x, lr=0.2, optimizer=OptimizerOptions("adam"), progress=False)


def test_increment_is_a_transitions_keyword():
    x = torch.zeros(10, 2, dtype=DT)
    with pytest.raises(InputError, match=r"unexpected keyword argument\(s\) \['increment'\]"):
        GPMeasurement.fit(x, x[:, :1], increment=False)
