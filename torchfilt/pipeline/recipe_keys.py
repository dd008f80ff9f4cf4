"""One recipe key of :data:`~torchfilt.pipeline.recipe.RECIPE_SCHEMA`: its default, meaning and
allowed values, and the check that names the file, the table and the key; and what a recipe's
digest keeps of a table whose keys were added after recipes were first digested."""

from __future__ import annotations

import copy
import math
from collections.abc import Collection, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from torchfilt.exceptions import RecipeError

__all__ = ["Key", "digested"]


@dataclass(frozen=True)
class Key:
    """One recipe key: its name, its default as written in the reference, what it means, and the
    values it takes (checked when the recipe is loaded, before any training).

    Attributes:
        name: the key.
        default: the default, as the reference shows it.
        meaning: what it does.
        kind: ``"any"`` (checked later, against the dataset or by the fit), ``"bool"``,
            ``"int"``, ``"posint"`` (an integer >= 1), ``"nonnegint"`` (an integer >= 0),
            ``"posfloat"`` (a finite number > 0), ``"nonnegfloat"`` (a finite number >= 0) or
            ``"choice"`` (one of ``choices``).
        choices: the allowed strings of a ``"choice"`` key.
    """

    name: str
    default: str
    meaning: str
    kind: str = "any"
    choices: tuple[str, ...] = ()

    @property
    def allowed(self) -> str:
        """The allowed values, as the reference shows them."""
        return {
            "bool": "`true`, `false`",
            "int": "an integer",
            "posint": "an integer >= 1",
            "nonnegint": "an integer >= 0",
            "posfloat": "a number > 0",
            "nonnegfloat": "a number >= 0",
            "choice": ", ".join(f'`"{c}"`' for c in self.choices),
        }.get(self.kind, "")

    def check(self, value: Any, where: str, path: Path | None) -> None:
        """Raise :class:`RecipeError` naming the file, the table and the key if ``value`` is not
        one of the allowed values."""
        number = isinstance(value, int | float) and not isinstance(value, bool)
        ok = {
            "bool": isinstance(value, bool),
            "int": isinstance(value, int) and not isinstance(value, bool),
            "posint": isinstance(value, int) and not isinstance(value, bool) and value >= 1,
            "nonnegint": isinstance(value, int) and not isinstance(value, bool) and value >= 0,
            "posfloat": number and math.isfinite(value) and value > 0,
            "nonnegfloat": number and math.isfinite(value) and value >= 0,
            "choice": value in self.choices,
        }.get(self.kind, True)
        if not ok:
            raise RecipeError(
                f"{_file(path)}[{where}] {self.name} must be {self.allowed.replace('`', '')}, "
                f"got {value!r}"
            )


def _file(path: Path | None) -> str:
    """The ``"FILE: "`` prefix of a message (none for a recipe built in code)."""
    return "" if path is None else f"{path}: "


def digested(
    table: Mapping[str, Any], later: Collection[str], defaults: Mapping[str, Any]
) -> dict[str, Any]:
    """A copy of a recipe ``table`` without its ``later`` keys (added after recipes were first
    digested) where they hold their ``defaults``: the digests of earlier recipes stay the same."""
    return {k: copy.deepcopy(v) for k, v in table.items() if k not in later or v != defaults[k]}
