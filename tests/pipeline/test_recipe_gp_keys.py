"""The recipe's GP keys are the GP fits' keywords (issue 23): every key of ``[transition]`` and
``[measurement]`` but ``model`` (and ``R``, an entry point's) is a keyword of ``GPTransition.fit``
or ``GPMeasurement.fit`` (``lr`` a field of its ``optimizer=``), the default the reference shows
is the signature's, a key's allowed choices are the keyword's ``Literal`` values, and the
pipeline's call builds the fit's keywords from a recipe table."""

from __future__ import annotations

import inspect
import tomllib
import typing
from typing import Any

import pytest

from torchfilt.optim import DEFAULTS, OptimizerOptions
from torchfilt.pipeline.recipe import GP_OPTIONS, OPTION_KEYS, RECIPE_SCHEMA, fit_options

gp = pytest.importorskip("torchfilt.models.gp")

FITS = {"transition": gp.GPTransition.fit, "measurement": gp.GPMeasurement.fit}
#: Keys of a GP side that are no fit option: the known model instead of a GP, and its noise.
NOT_OPTIONS = {"model", "R"}


def gp_keys(section: str) -> dict[str, Any]:
    return {k.name: k for k in RECIPE_SCHEMA[section] if k.name not in NOT_OPTIONS}


def shown_value(text: str) -> Any:
    """The value a reference default shows: a TOML literal in backquotes, or a parenthesised
    word (``(none)``, ``(all)``, ``(learned)``) for ``None``."""
    if text.startswith("("):
        return None
    return tomllib.loads(f"v = {text.strip('`')}")["v"]


def signature_default(section: str, key: str) -> Any:
    """What the fit uses when the recipe leaves ``key`` out: the signature's default, or, for an
    option field whose keyword defaults to ``None``, the GP fit's entry of ``DEFAULTS``."""
    params = inspect.signature(FITS[section]).parameters
    if key in OPTION_KEYS:
        cls, field = OPTION_KEYS[key]
        group = "optimizer" if cls is OptimizerOptions else field
        assert params[group].default is None, (section, key)
        d = DEFAULTS["gp"]
        return getattr(d.optimizer if cls is OptimizerOptions else d, field)
    return params[key].default


@pytest.mark.parametrize("section", sorted(FITS))
def test_every_gp_key_is_a_keyword_of_the_fit(section):
    params = inspect.signature(FITS[section]).parameters
    for key in gp_keys(section):
        if key in OPTION_KEYS:
            cls, _ = OPTION_KEYS[key]
            assert cls is OptimizerOptions or key == "iterations", key
            assert ("optimizer" if cls is OptimizerOptions else key) in params, (section, key)
        else:
            assert params[key].kind is inspect.Parameter.KEYWORD_ONLY, (section, key)
    assert ("increment" in gp_keys(section)) == (section == "transition")
    assert frozenset(gp_keys("transition")) == GP_OPTIONS


@pytest.mark.parametrize("section", sorted(FITS))
def test_each_default_shown_is_the_signatures(section):
    for name, key in gp_keys(section).items():
        assert shown_value(key.default) == signature_default(section, name), (section, name)


@pytest.mark.parametrize("section", sorted(FITS))
def test_each_choice_key_allows_the_keywords_literal_values(section):
    hints = typing.get_type_hints(FITS[section])
    for name, key in gp_keys(section).items():
        if key.kind == "choice":
            assert set(key.choices) == set(typing.get_args(hints[name])), (section, name)


def test_a_recipe_table_becomes_the_fits_keywords():
    """As ``run_stages`` calls the fit: the table's option fields become ``iterations=`` and
    ``optimizer=``, every other key passes through, and each is a keyword of the fit."""
    table = {"kernel": "matern52", "iterations": 7, "lr": 0.02, "subset": 50}
    kw = {k: v for k, v in table.items() if k not in OPTION_KEYS} | fit_options(table, "gp")
    assert kw == {
        "kernel": "matern52",
        "subset": 50,
        "iterations": 7,
        "optimizer": OptimizerOptions("adam", lr=0.02),
    }
    params = inspect.signature(FITS["transition"]).parameters
    assert set(kw) <= set(params)
