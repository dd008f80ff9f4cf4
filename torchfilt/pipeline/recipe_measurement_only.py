"""The ``[measurement_only]`` table of a ``states = "none"`` recipe: its defaults and the checks
that follow the per-key ones of :data:`~torchfilt.pipeline.recipe.RECIPE_SCHEMA` (the options of
the chosen method, the known channels, the nominal model, the process noise, and a learned
sensor noise, which needs a sensor of your own with its ``R``)."""

from __future__ import annotations

import math
from typing import Any

from torchfilt.exceptions import RecipeError
from torchfilt.pipeline.entry_point import is_entry_point
from torchfilt.pipeline.recipe_options import option_default

__all__ = ["EM_ONLY", "MEASUREMENT_ONLY_DEFAULTS", "check_learned_noise", "complete"]

#: Defaults of the ``[measurement_only]`` section (``states = "none"``; those of its option keys
#: from ``DEFAULTS["measurement_only"]``); ``None``: see
#: :data:`~torchfilt.pipeline.recipe.RECIPE_SCHEMA` (``known_channels``: all;
#: ``process_noise``: 1e-2 x the prior variances; ``window``: whole recordings; ``lr``: the
#: optimiser's default).
MEASUREMENT_ONLY_DEFAULTS: dict[str, Any] = {
    "method": "auto",
    **{
        k: option_default("measurement_only", k)
        for k in ("iterations", "optimizer", "lr", "window", "burn_in")
    },
    "inducing": 16,
    "known_channels": None,
    "nominal": None,
    "process_noise": None,
    "m_step_iterations": 20,
    "compile": False,
    "accelerate": False,
    "learn_measurement_noise": False,
    "stable": False,
}
#: The keys that only ``method = "em"`` (or ``"auto"``, ``"both"``) takes.
EM_ONLY = ("m_step_iterations", "accelerate")


def complete(mo: dict[str, Any]) -> dict[str, Any]:
    """``[measurement_only]`` whose keys and values passed the per-key checks, completed with
    its defaults and checked as a whole; a ``RecipeError`` names the key."""
    out = {**MEASUREMENT_ONLY_DEFAULTS, **mo}
    keys: tuple[str, ...] = ()  # "auto", "both" run both methods: they take the keys of both
    if out["method"] == "em":
        keys, other = ("window", "burn_in", "optimizer", "lr"), "likelihood"
    elif out["method"] == "likelihood":
        keys, other = EM_ONLY, "em"
    wrong = [k for k in keys if out[k] != MEASUREMENT_ONLY_DEFAULTS[k]]
    if wrong:
        raise RecipeError(
            f'[measurement_only] {wrong}: not an option of method = "{out["method"]}" (they '
            f'belong to method = "{other}"); remove them or change the method'
        )
    kc = out["known_channels"]
    if kc is not None and (
        not isinstance(kc, list)
        or not kc
        or not all(isinstance(c, str) and c for c in kc)
        or len(set(kc)) != len(kc)
    ):
        raise RecipeError(
            "[measurement_only] known_channels must be a non-empty list of distinct measurement "
            f"channel names, got {kc!r}"
        )
    nom = out["nominal"]
    if nom is not None and (not isinstance(nom, dict) or "system" not in nom):
        raise RecipeError(
            "[measurement_only] nominal must be a table with 'system' (and parameters), "
            f"got {nom!r}"
        )
    pn = out["process_noise"]
    if pn is not None:
        vals = pn if isinstance(pn, list) else [pn]
        if not vals or not all(
            isinstance(v, int | float) and not isinstance(v, bool) and math.isfinite(v) and v > 0
            for v in vals
        ):
            raise RecipeError(
                "[measurement_only] process_noise must be a number > 0 or a list of them (one "
                f"per state), got {pn!r}"
            )
    if out["stable"] and (nom is not None or pn is not None):
        raise RecipeError(
            "[measurement_only] stable = true acts on the linear-EM start, which "
            + ("a nominal model" if nom is not None else "a given process_noise")
            + " replaces (it is the start): remove one of them"
        )
    if out["window"] is not None and not 0 <= out["burn_in"] < out["window"]:
        raise RecipeError(
            f"[measurement_only] burn_in must be an integer in [0, window), got {out['burn_in']!r}"
        )
    if out["lr"] is not None:
        out["lr"] = float(out["lr"])
    return out


def check_learned_noise(mo: dict[str, Any], measurement: dict[str, Any]) -> None:
    """``learn_measurement_noise = true`` needs a sensor of your own with its ``R`` (the start of
    the learned one): a built-in ``"system:NAME"`` sensor keeps its noise.

    Raises:
        RecipeError: naming both tables' keys.
    """
    if not mo.get("learn_measurement_noise"):
        return
    spec = measurement.get("model")
    if not is_entry_point(spec) or measurement.get("R") is None:
        raise RecipeError(
            "[measurement_only] learn_measurement_noise = true learns the noise of your own "
            f'sensor from its start [measurement] R; [measurement] model = "{spec}" '
            + ("has no R: give R (the start)" if is_entry_point(spec) else "is a built-in")
            + ' (use model = "package.module:function" with R, or learn_measurement_noise = '
            "false)"
        )
