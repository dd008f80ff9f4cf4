"""The recipe keys that are the fits' options: which option field each flat key of
``[calibrate]`` and ``[measurement_only]`` sets, its default (the fit's, from
:data:`~torchfilt.optim.DEFAULTS`), and the fit's option groups built from a recipe table. The
recipe schema (:mod:`torchfilt.pipeline.recipe`) and its reference take their defaults and
meanings from here and from the option dataclasses, so the recipe, the Python API and the
reference cannot drift apart."""

from __future__ import annotations

from collections.abc import Collection, Mapping
from dataclasses import replace
from typing import Any

from torchfilt.optim import DEFAULTS, FitDefaults, OptimizerOptions, StoppingOptions, WindowOptions

__all__ = ["OPTION_KEYS", "fit_options", "option_default"]

#: The recipe keys that are fields of the fits' options (:mod:`torchfilt.optim.options`): key ->
#: (its class, its field). The recipe tables stay flat (``lr = 0.1`` under ``[calibrate]``);
#: :func:`fit_options` builds the option groups from them, and each key's default and meaning
#: in :data:`RECIPE_SCHEMA` come from the fit's :data:`~torchfilt.optim.DEFAULTS` and the field's
#: docstring.
OPTION_KEYS: dict[str, tuple[type, str]] = {
    "iterations": (FitDefaults, "iterations"),
    "optimizer": (OptimizerOptions, "optimizer"),
    "lr": (OptimizerOptions, "lr"),
    "window": (WindowOptions, "window"),
    "burn_in": (WindowOptions, "burn_in"),
    "patience": (StoppingOptions, "patience"),
    "atol": (StoppingOptions, "atol"),
    "per_iteration": (WindowOptions, "per_iteration"),
}


def option_default(fit: str, key: str) -> Any:
    """The default of option key ``key`` (of :data:`OPTION_KEYS`) of fit ``fit``, from
    :data:`~torchfilt.optim.DEFAULTS`."""
    d = DEFAULTS[fit]
    cls, name = OPTION_KEYS[key]
    if cls is FitDefaults:
        return getattr(d, name)
    group = {OptimizerOptions: d.optimizer, WindowOptions: d.windows, StoppingOptions: d.stopping}
    return getattr(group[cls], name)


def fit_options(
    table: Mapping[str, Any], fit: str, given: Collection[str] | None = None
) -> dict[str, Any]:
    """The option keywords of fit ``fit`` (``iterations``, ``optimizer``, ``windows``,
    ``stopping``) from a flat recipe table: its keys of :data:`OPTION_KEYS`, each set on its
    option group over the fit's defaults. A ``patience`` counts (early stopping without held-out
    data then warns) only when the recipe set it: a key in ``given`` (the keys the recipe file
    wrote; ``None``: those of ``table`` that differ from the default)."""
    if given is None:
        given = {k for k, v in table.items() if k in OPTION_KEYS and v != option_default(fit, k)}
    groups: dict[type, dict[str, Any]] = {}
    out: dict[str, Any] = {}
    for key, (cls, name) in OPTION_KEYS.items():
        if key not in table or (cls is StoppingOptions and key not in given):
            continue
        if cls is FitDefaults:
            out[name] = int(table[key])
        else:
            groups.setdefault(cls, {})[name] = table[key]
    d = DEFAULTS[fit]
    if OptimizerOptions in groups:
        out["optimizer"] = replace(d.optimizer, **groups[OptimizerOptions])
    if WindowOptions in groups:
        out["windows"] = replace(d.windows, **groups[WindowOptions])
    if StoppingOptions in groups:
        out["stopping"] = StoppingOptions(**groups[StoppingOptions])
    return out
