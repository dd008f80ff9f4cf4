"""The docs build's griffe extensions (scripts/griffe_docs.py): Sphinx roles in docstrings become
autorefs links resolved as Sphinx would, no role in the package names something that does not
exist (a typo would otherwise render silently as plain code), and deprecated aliases leave the
API pages."""

from __future__ import annotations

from pathlib import Path

import pytest
from script_support import load_script

griffe = pytest.importorskip("griffe")
roles = load_script("griffe_docs")


@pytest.fixture(scope="module")
def package():
    return griffe.load("torchfilt", search_paths=[str(Path(__file__).resolve().parents[2])])


def test_every_role_in_the_package_resolves(package):
    assert roles.unresolved(package) == []


def test_relative_names_resolve_in_the_docstrings_scope(package):
    update = package["filters.gaussian.GaussianFilter.update"]
    html = roles.convert(update, "see :meth:`predict` and :class:`~torchfilt.FilterResult`")
    assert 'identifier="torchfilt.filters.gaussian.GaussianFilter.predict"' in html
    assert "<code>predict()</code>" in html
    assert "<code>FilterResult</code>" in html  # the tilde shows the last component only
    assert ":meth:" not in html and ":class:" not in html


def test_external_and_unknown_names_render_as_code(package):
    obj = package["filters.gaussian.GaussianFilter"]
    assert roles.convert(obj, ":class:`torch.Tensor`") == "`torch.Tensor`"
    assert roles.convert(obj, ":func:`no_such_name`") == "`no_such_name()`"
    bogus = roles.convert(obj, ":func:`~torchfilt.filters.no_such_function`")
    assert "optional><code>no_such_function()</code>" in bogus  # never a hard link: see unresolved


def test_a_misspelt_target_is_reported(package):
    obj = package["filters.gaussian.GaussianFilter"]
    obj.docstring.value += "\n\nSee :func:`torchfilt.filters.kalman.kalman_filterr`."
    try:
        assert (
            "torchfilt.filters.gaussian.GaussianFilter",
            "torchfilt.filters.kalman.kalman_filterr",
        ) in roles.unresolved(package)
    finally:
        obj.docstring.value = obj.docstring.value.rsplit("\n\nSee ", 1)[0]


def test_deprecated_aliases_leave_the_pages_and_current_names_stay():
    pkg = griffe.load("torchfilt", search_paths=[str(Path(__file__).resolve().parents[2])])
    gaussian = pkg["filters.gaussian.GaussianFilter"]
    assert roles.is_deprecated(gaussian.members["loop_fallback"])
    roles.HideDeprecated().on_package(pkg=pkg)
    for old in ("loop_fallback", "prepare", "run", "scan", "step_function", "execution"):
        assert old not in gaussian.members
    for current in ("filter", "smooth", "init", "predict", "update"):
        assert current in gaussian.members
