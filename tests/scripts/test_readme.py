"""The README's Python examples run as written.

A block preceded by the HTML comment ``<!-- test: slow -->`` (e.g. one that trains GPs on a realistic
log) runs with the slow tests only (``make test-slow``).
"""

import re
from pathlib import Path

import matplotlib
import pytest

matplotlib.use("Agg")

README = Path(__file__).resolve().parents[2] / "README.md"
BLOCKS = [
    (bool(slow), code)
    for slow, code in re.findall(
        r"(<!-- test: slow -->\s*)?```python\n(.*?)```", README.read_text(), re.S
    )
]


def test_readme_has_examples():
    assert BLOCKS


@pytest.mark.parametrize(
    "i",
    [pytest.param(i, marks=pytest.mark.slow) if slow else i for i, (slow, _) in enumerate(BLOCKS)],
)
def test_readme_example_runs(i, tmp_path, monkeypatch):
    monkeypatch.chdir(Path(__file__).resolve().parents[2])
    exec(compile(BLOCKS[i][1], f"README.md block {i}", "exec"), {"__name__": "__readme__"})
