"""The recipe's option keys are the fits' options (issue 23): each key's default is its fit's
default, the reference shows each option field with its meaning from the dataclass, and a flat
recipe table becomes the fit's option groups without a hand-written mapping."""

from __future__ import annotations

import inspect
from pathlib import Path

import pytest

from torchfilt.optim import (
    FitDefaults,
    OptimizerOptions,
    StoppingOptions,
    WindowOptions,
    field_docs,
    resolve_options,
)
from torchfilt.pipeline.recipe import (
    CALIBRATE_DEFAULTS,
    MEASUREMENT_ONLY_DEFAULTS,
    OPTION_KEYS,
    RECIPE_SCHEMA,
    fit_options,
    load_recipe,
    recipe_reference,
)

ROOT = Path(__file__).resolve().parents[2]
SECTIONS = {"calibrate": CALIBRATE_DEFAULTS, "measurement_only": MEASUREMENT_ONLY_DEFAULTS}


def python_default(fit: str, key: str) -> object:
    """What the Python fit uses when the key's option is not given."""
    o = resolve_options(fit)
    return {
        "iterations": o.iterations,
        "optimizer": o.optimizer.optimizer,
        "lr": o.optimizer.lr,
        "window": o.windows.window,
        "burn_in": o.windows.burn_in,
        "patience": o.stopping.patience,
        "atol": o.stopping.atol,
        "per_iteration": o.windows.per_iteration,
    }[key]


def shown(value: object) -> str:
    return f'`"{value}"`' if isinstance(value, str) else f"`{value}`"


@pytest.mark.parametrize("section", sorted(SECTIONS))
def test_every_option_key_defaults_to_its_fits_default(section):
    keys = {k.name: k for k in RECIPE_SCHEMA[section]}
    options = [k for k in OPTION_KEYS if k in keys]
    assert {"iterations", "window", "burn_in", "optimizer", "lr"} <= set(options)
    for key in options:
        want = python_default(section, key)
        assert SECTIONS[section][key] == want, (section, key)
        if want is not None:
            assert keys[key].default == shown(want), (section, key, keys[key].default)
    assert CALIBRATE_DEFAULTS["iterations"] == 100  # what `torchfilt train` has always run


@pytest.mark.parametrize("section", ["transition", "measurement"])
def test_the_gp_sections_budget_and_rate_are_the_gp_fits(section):
    from torchfilt.models.gp import GPModel

    keys = {k.name: k for k in RECIPE_SCHEMA[section]}
    assert keys["iterations"].default == shown(python_default("gp", "iterations")) == "`200`"
    assert keys["lr"].default == shown(python_default("gp", "lr")) == "`0.05`"
    assert inspect.signature(GPModel.optimize).parameters["iterations"].default is None


def test_the_reference_shows_each_option_field_with_its_doc():
    ref = recipe_reference()
    for section in SECTIONS:
        part = ref.split(f"## `[{section}]`")[1].split("\n## ")[0]
        for key in (k.name for k in RECIPE_SCHEMA[section] if k.name in OPTION_KEYS):
            cls, name = OPTION_KEYS[key]
            doc = field_docs(cls)[name]
            assert doc and f"| `{key}` |" in part and doc in part, (section, key)
    for cls in (OptimizerOptions, WindowOptions, StoppingOptions, FitDefaults):
        assert set(field_docs(cls)) >= {name for c, name in OPTION_KEYS.values() if c is cls}


def _recipe(tmp_path: Path, calibrate: str) -> Path:
    p = tmp_path / "r.toml"
    p.write_text(
        '[dataset]\npath = "d"\n[transition]\nkernel = "rbf"\n[measurement]\nkernel = "rbf"\n'
        f"[calibrate]\n{calibrate}"
    )
    return p


def test_a_flat_table_becomes_the_option_groups(tmp_path):
    r = load_recipe(_recipe(tmp_path, "lr = 0.3\nwindow = 50\niterations = 7\n"))
    assert r.calibrate["lr"] == 0.3 and r.calibrate["burn_in"] == 20  # flat, defaults filled
    opts = fit_options(r.calibrate, "calibrate", r.given["calibrate"])  # type: ignore[index]
    assert opts == {
        "iterations": 7,
        "optimizer": OptimizerOptions("adam", lr=0.3),
        "windows": WindowOptions(window=50, burn_in=20, per_iteration=64),
    }  # no "stopping": the recipe did not set patience
    assert resolve_options("calibrate", **opts).stopping.patience == 15
    assert not resolve_options("calibrate", **opts).patience_given
    # written in the recipe, even at its default: given (early stopping without held-out
    # recordings then warns)
    r2 = load_recipe(_recipe(tmp_path, "patience = 15\n"))
    opts2 = fit_options(r2.calibrate, "calibrate", r2.given["calibrate"])  # type: ignore[index]
    assert opts2["stopping"] == StoppingOptions(patience=15)
    assert resolve_options("calibrate", **opts2).patience_given
    # the digest of a recipe that writes the defaults equals that of one that does not
    assert r2.digest() == load_recipe(_recipe(tmp_path, "")).digest()


@pytest.mark.parametrize("path", sorted((ROOT / "trainers").glob("*.toml")), ids=lambda p: p.name)
def test_shipped_recipes_build_their_fit_options(path):
    r = load_recipe(path)
    opts = fit_options(r.calibrate, "calibrate", r.given["calibrate"])  # type: ignore[index]
    resolve_options("calibrate", **opts)
    if r.states == "none":
        mo = fit_options(r.measurement_only, "measurement_only")
        resolve_options("measurement_only", **mo)
