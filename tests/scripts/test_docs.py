"""The documentation is exercised: the recipe reference matches the schema the validator uses,
the bring-your-own-data walkthrough runs as written, from CSV files to a plot, and every code
block of the other pages under docs/ runs.

Code blocks of the pages (the conventions of tests/scripts/test_readme.py, extended):

- ```python runs as written, from the repository root, each block in a fresh namespace; one
  preceded by the HTML comment ``<!-- test: slow -->`` (it trains for minutes) runs with the
  slow tests only (``make test-slow``).
- ```sh lists commands: each ``torchfilt SUB ... --flag`` names a sub-command whose ``--help``
  lists every flag used, ``python scripts/X.py`` an existing script, ``make T`` a Makefile target.
- ```toml parses as TOML.
- ```text is output (tables printed by the scripts) and is not run.

Any other fence (or none) is an error, so no block goes unchecked. docs/byod.md has its own test
above; docs/recipes.md is generated.
"""

from __future__ import annotations

import contextlib
import io
import re
import shlex
import tomllib
from pathlib import Path

import matplotlib
import pytest

from torchfilt.cli import main
from torchfilt.pipeline import load_recipe
from torchfilt.pipeline.recipe import RECIPE_SCHEMA, Recipe, recipe_reference
from torchfilt.training import RecipeError

matplotlib.use("Agg")

ROOT = Path(__file__).resolve().parents[2]
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


DOCS = ROOT / "docs"
OWN_TESTS = {BYOD, DOCS / "recipes.md"}
PAGES = sorted(p for p in DOCS.rglob("*.md") if p not in OWN_TESTS)
FENCE = re.compile(r"(<!-- test: slow -->\s*)?^```(\S*)\n(.*?)^```", re.S | re.M)
KINDS = {"python", "sh", "toml", "text"}


def _blocks(page: Path) -> list[tuple[str, str, bool]]:
    """(kind, body, slow) for each fenced block of a page."""
    return [(kind, body, bool(slow)) for slow, kind, body in FENCE.findall(page.read_text())]


BLOCKS = [
    (page.relative_to(DOCS).as_posix(), i, kind, body, slow)
    for page in PAGES
    for i, (kind, body, slow) in enumerate(_blocks(page))
]


def test_the_pages_have_examples_and_every_fence_is_known():
    assert any(kind == "python" for _, _, kind, _, _ in BLOCKS)
    unknown = [(page, i, kind) for page, i, kind, _, _ in BLOCKS if kind not in KINDS]
    assert not unknown, f"fences without a known language {sorted(KINDS)}: {unknown}"


@pytest.mark.parametrize(
    ("page", "i"),
    [
        pytest.param(page, i, marks=[pytest.mark.slow] if slow else [], id=f"{page}-{i}")
        for page, i, kind, _, slow in BLOCKS
        if kind == "python"
    ],
)
def test_page_python_block_runs(page, i, monkeypatch):
    monkeypatch.chdir(ROOT)
    body = next(b for p, j, _, b, _ in BLOCKS if (p, j) == (page, i))
    exec(compile(body, f"docs/{page} block {i}", "exec"), {"__name__": "__docs__"})


def _help(sub: str) -> str:
    out = io.StringIO()
    with contextlib.redirect_stdout(out), pytest.raises(SystemExit) as e:
        main([sub, "--help"])
    assert e.value.code == 0, sub
    return out.getvalue()


def _check_command(line: str, targets: set[str]) -> None:
    args = shlex.split(line, comments=True)
    if not args:
        return
    if args[0] == "torchfilt":
        help_text = _help(args[1])
        flags = [a.split("=")[0] for a in args[2:] if a.startswith("--")]
        missing = [f for f in flags if f not in help_text]
        assert not missing, f"{line!r}: `torchfilt {args[1]}` has no {missing}"
    elif args[0] == "python" and args[1].startswith("scripts/"):
        assert (ROOT / args[1]).is_file(), line
    elif args[0] == "make":
        assert args[1] in targets, line


@pytest.mark.parametrize(
    ("page", "i"),
    [pytest.param(p, i, id=f"{p}-{i}") for p, i, kind, _, _ in BLOCKS if kind in ("sh", "toml")],
)
def test_page_command_and_toml_blocks_are_current(page, i):
    kind, body = next((k, b) for p, j, k, b, _ in BLOCKS if (p, j) == (page, i))
    if kind == "toml":
        tomllib.loads(body)
        return
    targets = set(re.findall(r"^([\w-]+):", (ROOT / "Makefile").read_text(), re.M))
    for line in body.splitlines():
        _check_command(line, targets)
