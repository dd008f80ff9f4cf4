"""The guide page ``docs/guide/own-system.md`` runs as written: its files (the sensor module and
the recipe, each after a ``<!-- file: NAME -->`` marker) are written to a folder, and its
``torchfilt`` commands run there in order (the recipe with fewer iterations and inducing points);
the log says what the page says it says."""

from __future__ import annotations

import re
import shlex
from pathlib import Path

import pytest

from torchfilt.cli import main as cli_main

PAGE = Path(__file__).resolve().parents[2] / "docs" / "guide" / "own-system.md"
FILE = re.compile(r"<!-- file: (\S+) -->\n```\w*\n(.*?)```", re.S)
BASH = re.compile(r"```sh\n(.*?)```", re.S)


def test_the_own_system_page_runs_as_written(tmp_path, monkeypatch, capsys) -> None:
    text = PAGE.read_text()
    files = dict(FILE.findall(text))
    assert set(files) == {"my_sensor.py", "own.toml"}
    recipe = files["own.toml"].replace("iterations = 30", "iterations = 2")
    recipe = recipe.replace("inducing = 16", "inducing = 4")
    assert recipe != files["own.toml"]
    (tmp_path / "my_sensor.py").write_text(files["my_sensor.py"])
    (tmp_path / "own.toml").write_text(recipe)
    monkeypatch.chdir(tmp_path)
    monkeypatch.syspath_prepend(str(tmp_path))  # the page's PYTHONPATH=.
    commands = [line for block in BASH.findall(text) for line in block.splitlines() if line]
    assert len(commands) == 5
    for line in commands:
        argv = shlex.split(line.removeprefix("PYTHONPATH=. "))
        assert argv[0] == "torchfilt", line
        assert cli_main(argv[1:]) == 0, line
    log = (tmp_path / "run" / "train.log").read_text()
    assert (
        "transition: learning from measurements alone (auto, 4 inducing points, known channels "
        "['pressure'])" in log
    )
    assert re.search(r"validation filter \(\w+\): NIS [\d.]+ per 1 dof", log)
    assert "measurement_only" in capsys.readouterr().out  # torchfilt info shows the fit record
    assert any((tmp_path / "est").iterdir())


def test_the_page_is_in_the_site_navigation() -> None:
    nav = (PAGE.parents[2] / "mkdocs.yml").read_text()
    assert "guide/own-system.md" in nav


@pytest.mark.parametrize("name", ["my_sensor.py", "own.toml"])
def test_the_page_files_are_complete(name: str) -> None:
    files = dict(FILE.findall(PAGE.read_text()))
    assert files[name].strip()
