"""Hypothesis suite over ``load_recipe`` (the recipe every ``torchfilt train`` reads): random
tables of known and unknown keys with values of every TOML kind (booleans, integers, floats
with NaN and infinity, strings, lists, tables) are either loaded or refused with a RecipeError
that names the file; a loaded recipe holds every value the file gave. See tests/fuzz_support.py
for the contract."""

from __future__ import annotations

import json
import math
import tempfile
from pathlib import Path
from typing import Any

from fuzz_support import Refused, attempt, print_stats, property_tests
from hypothesis import strategies as st

from torchfilt.exceptions import RecipeError
from torchfilt.pipeline.recipe import RECIPE_SCHEMA, load_recipe

_SCALARS = st.one_of(
    st.booleans(),
    st.integers(-3, 300),
    st.floats(allow_nan=True, allow_infinity=True, width=64),
    st.sampled_from(["em", "likelihood", "lbfgs", "adam", "auto", "none", "logged", "rbf", ""]),
    st.sampled_from(["system:reaction", "system:nope", "pkg.mod:fn", "not a spec"]),
)
_VALUES = st.one_of(
    _SCALARS,
    st.lists(
        st.one_of(st.integers(-2, 5), st.floats(-1, 1), st.text("ab", max_size=2)), max_size=3
    ),
    st.just({"system": "reaction", "k1": 0.08}),
    st.just({"k1": 0.08}),
)


def _toml(v: Any) -> str:
    """A TOML value (inline tables and arrays; a mixed array is valid TOML 1.0)."""
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, float):
        return (
            "nan" if math.isnan(v) else ("inf" if v > 0 else "-inf") if math.isinf(v) else repr(v)
        )
    if isinstance(v, int):
        return str(v)
    if isinstance(v, str):
        return json.dumps(v)
    if isinstance(v, list):
        return "[" + ", ".join(_toml(x) for x in v) + "]"
    return "{" + ", ".join(f"{k} = {_toml(x)}" for k, x in v.items()) + "}"


def _valid(kind: str, choices: tuple[str, ...]) -> st.SearchStrategy[Any]:
    """Values a key of ``kind`` allows (the checks of later stages may still refuse them)."""
    return {
        "bool": st.booleans(),
        "int": st.integers(-5, 50),
        "posint": st.integers(1, 50),
        "nonnegint": st.integers(0, 50),
        "posfloat": st.floats(1e-6, 10.0),
        "nonnegfloat": st.floats(0.0, 10.0),
        "choice": st.sampled_from(choices or ("",)),
    }.get(kind, _VALUES)


def _table(data: st.DataObject, section: str, extra: tuple[str, ...] = ()) -> dict[str, Any]:
    schema = {k.name: k for k in RECIPE_SCHEMA[section]}
    names = list(schema) + list(extra)
    keys = data.draw(st.lists(st.sampled_from(names), max_size=3, unique=True), label=section)
    out = {}
    for k in keys:
        key = schema.get(k)
        valid = key is not None and data.draw(
            st.sampled_from([True] * 6 + [False]), label=f"{section}.{k} valid"
        )
        values = _valid(key.kind, key.choices) if valid and key is not None else _VALUES
        out[k] = data.draw(values, label=f"{section}.{k}")
    return out


#: the tables of a recipe (their names are keys of the top level too)
_TABLES = (
    "dataset",
    "transition",
    "measurement",
    "filter",
    "measurement_only",
    "calibrate",
    "train",
)


def _side(data: st.DataObject, section: str, states: str) -> dict[str, Any]:
    """A known model (the measurement's own sensor with its R, too), or GP options."""
    known = [{"model": "system:reaction"}]
    if section == "measurement":
        known.append({"model": "pkg.mod:fn", "R": [0.01]})
    if states == "none" or data.draw(st.booleans(), label=f"{section} known"):
        return data.draw(st.sampled_from(known), label=section)
    return _table(data, section, ("bogus",) if data.draw(st.integers(0, 9)) == 0 else ())


def _check(data: st.DataObject) -> None:
    states = data.draw(st.sampled_from(["logged", "none"] * 4 + ["maybe"]), label="states")
    top: dict[str, Any] = {"states": states}
    top.update({k: v for k, v in _table(data, "").items() if k not in _TABLES})
    tables = {
        "dataset": {"path": "data", **_table(data, "dataset")},
        "transition": {} if states == "none" else _side(data, "transition", states),
        "measurement": _side(data, "measurement", states),
        "filter": {"prior": "system:reaction", **_table(data, "filter")},
        "measurement_only": _table(data, "measurement_only") if states == "none" else {},
        "calibrate": _table(data, "calibrate"),
        "train": _table(data, "train"),
    }
    lines = [f"{k} = {_toml(v)}" for k, v in top.items() if k not in tables]
    for name, t in tables.items():
        if t or (name in ("dataset", "measurement", "transition") and states != "none"):
            lines.append(f"[{name}]")
            lines += [f"{k} = {_toml(v)}" for k, v in t.items()]
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "fuzz.toml"
        path.write_text("\n".join(lines) + "\n")
        out, _ = attempt("load_recipe", load_recipe, path)
        if isinstance(out, Refused):
            assert isinstance(out.error, RecipeError), out
            assert str(out.error).startswith(f"{path}: "), out  # it names the file
            return
    # a loaded recipe holds what the file said (the values the checks let through, unchanged
    # but for lr, which is stored as a float)
    for k, v in tables["measurement_only"].items():
        got = out.measurement_only[k]
        same = got == v or (isinstance(v, float) and math.isnan(v) and math.isnan(got))
        assert same or (k == "lr" and got == float(v)), (k, v, got)


test_load_recipe_short, test_load_recipe_long = property_tests(_check, short=60, long=1500)


def teardown_module() -> None:
    print_stats()
