"""The documentation is exercised: the recipe reference matches the schema the validator uses,
and the bring-your-own-data walkthrough runs as written, from CSV files to a plot."""

from __future__ import annotations

import re
import shlex
from pathlib import Path

import matplotlib
import pytest

from torchfilt.cli import main
from torchfilt.pipeline import load_recipe
from torchfilt.pipeline.recipe import RECIPE_SCHEMA, Recipe, recipe_reference
from torchfilt.training import RecipeError

matplotlib.use("Agg")

ROOT = Path(__file__).resolve().parents[1]
BYOD = ROOT / "docs" / "byod.md"


def test_recipe_reference_is_generated_from_the_schema():
    assert (ROOT / "docs" / "recipes.md").read_text() == recipe_reference(), (
        "docs/recipes.md is stale: run python scripts/make_docs.py"
    )


def _minimal(section: str, key: str) -> str:
    tables = {"dataset": {"path": "'d'"}, "transition": {}, "measurement": {}}
    value = "'x'"
    if section in ("", None):
        extra = f"{key} = {value}\n" if key not in tables and key not in ("train", "filter") else ""
    else:
        tables.setdefault(section, {})[key] = value
        extra = ""
    body = extra + "".join(
        f"[{name}]\n" + "".join(f"{k} = {v}\n" for k, v in keys.items())
        for name, keys in tables.items()
    )
    return body


@pytest.mark.parametrize(
    ("section", "key"),
    [(s, k.name) for s, keys in RECIPE_SCHEMA.items() for k in keys if s and k.name != "model"],
)
def test_every_documented_key_is_accepted_and_a_typo_is_not(tmp_path, section, key):
    p = tmp_path / "r.toml"
    p.write_text(_minimal(section, key))
    try:
        load_recipe(p)
    except RecipeError as e:
        assert "unknown key" not in str(e), e  # a value error is fine: the key was accepted
    p.write_text(_minimal(section, key + "_typo"))
    with pytest.raises(RecipeError, match=rf"unknown key\(s\) \['{key}_typo'\] in \[{section}\]"):
        load_recipe(p)


def test_documented_train_defaults_are_the_code_defaults():
    doc = {k.name: k.default for k in RECIPE_SCHEMA["train"]}
    fields = Recipe.__dataclass_fields__
    assert doc["checkpoint_every"] == f"`{fields['checkpoint_every'].default}`"
    assert doc["dtype"] == f'`"{fields["dtype"].default}"`'


def _steps(text: str) -> list[tuple[str, str, str | None]]:
    """(kind, body, file) for each code block: python, sh, or a file to write."""
    out = []
    pattern = r"(?:<!-- file: (\S+) -->\s*)?```(\w+)\n(.*?)```"
    for file, kind, body in re.findall(pattern, text, re.S):
        out.append(("file" if file else kind, body, file or None))
    return out


def test_byod_walkthrough_runs_from_csv_to_plot(tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    steps = _steps(BYOD.read_text())
    assert [k for k, _, _ in steps] == ["python", "file", "file", "sh"]
    commands = 0
    for kind, body, file in steps:
        if kind == "python":
            exec(compile(body, "docs/byod.md", "exec"), {"__name__": "__byod__"})
        elif kind == "file":
            assert file is not None
            Path(file).write_text(body)
        else:
            for line in body.strip().splitlines():
                args = shlex.split(line)
                assert args[0] == "torchfilt"
                assert main(args[1:]) == 0, line
                commands += 1
    assert commands == 3
    out = capsys.readouterr().out
    assert "smoothed estimates, 1 recordings" in out and "position: RMSE" in out
    est = tmp_path / "runs" / "cart_est"
    for name in ("log_5.filtered.csv", "log_5.smoothed.csv", "log_5.png"):
        assert (est / name).is_file(), name
    assert (est / "log_5.png").stat().st_size > 10_000
