"""griffe extensions of the documentation site: Sphinx roles become links, deprecated aliases
leave the API pages.

**Roles.**

torchfilt's docstrings cross-reference in Sphinx's spelling (``:func:`~torchfilt.fit_em```,
``:class:`FilterResult```, ``:meth:`predict```), which reads well in ``help()`` and in an editor.
mkdocstrings renders Markdown, where such a role shows literally. This griffe extension, loaded by
``mkdocs.yml`` (``extensions: [scripts/griffe_docs.py]``), rewrites each role, once the whole
package is loaded, into an autorefs cross-reference:

* a leading ``~`` shows only the last component, as in Sphinx; ``:func:`` and ``:meth:`` add
  ``()``;
* a relative name (``predict``, ``FilterResult.mean``) is resolved in the scope of the object
  whose docstring holds it (its members, its class, its module and what that imports), as Sphinx
  does;
* the reference is *optional*: a target the site does not render (``torch.Tensor``, a private
  helper) shows as code without a link instead of failing the strict build. Typos are caught by
  :func:`unresolved`, which ``tests/scripts/test_griffe_docs.py`` requires to be empty.

**Deprecated aliases.** A member whose docstring starts with "Deprecated" (the one-release
aliases of renamed methods and properties, which warn when used) is left out of the API pages, so
a reader sees each idea under its current name only; the CHANGELOG lists the old names.

Not part of the package (only the docs build imports it).
"""

from __future__ import annotations

import re
from collections.abc import Iterator
from typing import Any

import griffe

#: ``:role:`target``` or ``:role:`~target``` (``:py:role:`` too); the target has no spaces.
ROLE = re.compile(
    r":(?:py:)?(?P<role>func|class|meth|data|mod|attr|exc|obj|const):`(?P<tilde>~?)(?P<target>[^`\s<>]+)`"
)
#: Roles shown with call parentheses, as Sphinx's ``add_function_parentheses`` does.
CALLABLE = ("func", "meth")
#: Roots whose names are not this package's (shown as code, never looked up).
EXTERNAL = (
    "torch",
    "numpy",
    "np",
    "scipy",
    "gpytorch",
    "ray",
    "matplotlib",
    "dataclasses",
    "typing",
    "contextvars",
    "warnings",
)


def resolve(obj: griffe.Object, target: str) -> str | None:
    """The full path of ``target`` as seen from ``obj``'s docstring, or ``None`` if it names
    nothing in the loaded package (an external or misspelt name)."""
    if target.split(".")[0] in EXTERNAL:
        return None
    head, _, rest = target.partition(".")
    scope: griffe.Object | None = obj
    while scope is not None:
        full = _in_scope(scope, head)
        if full is not None:
            return f"{full}.{rest}" if rest else full
        scope = scope.parent
    return target if target.startswith("torchfilt") else None


def _in_scope(scope: griffe.Object, name: str) -> str | None:
    """``name`` resolved in ``scope`` (a class's inherited members included), or ``None``."""
    try:
        return scope.resolve(name)
    except (griffe.NameResolutionError, AttributeError, KeyError):
        pass
    if scope.is_class and name in scope.all_members:
        member = scope.all_members[name]
        try:
            return member.final_target.path if member.is_alias else member.path
        except (griffe.AliasResolutionError, griffe.CyclicAliasError):
            return None
    return None


def _render(obj: griffe.Object, match: re.Match[str]) -> str:
    target = match["target"].rstrip("()")
    shown = target.rsplit(".", 1)[-1] if match["tilde"] else target
    if match["role"] in CALLABLE:
        shown += "()"
    full = resolve(obj, target)
    if full is None:
        return f"`{shown}`"
    return f'<autoref identifier="{full}" optional><code>{shown}</code></autoref>'


def convert(obj: griffe.Object, text: str) -> str:
    """``text`` with every Sphinx role rewritten (see the module docstring)."""
    return ROLE.sub(lambda m: _render(obj, m), text)


def _objects(obj: griffe.Object) -> Iterator[griffe.Object]:
    yield obj
    for member in obj.members.values():
        if member.is_alias:
            continue
        yield from _objects(member)  # type: ignore[arg-type]


def unresolved(package: griffe.Object) -> list[tuple[str, str]]:
    """Every role in ``package``'s docstrings whose target is not external and names nothing:
    ``(object path, target)`` pairs."""
    bad = []
    for obj in _objects(package):
        if obj.docstring is None:
            continue
        for m in ROLE.finditer(obj.docstring.value):
            target = m["target"].rstrip("()")
            if target.split(".")[0] in EXTERNAL:
                continue
            full = resolve(obj, target)
            if full is None or not _exists(package, full):
                bad.append((obj.path, target))
    return bad


def _exists(package: griffe.Object, path: str) -> bool:
    parts = path.split(".")
    if parts[0] != package.name:
        return False
    node: Any = package
    for part in parts[1:]:
        try:
            node = node.members[part]
        except (KeyError, AttributeError, griffe.AliasResolutionError):
            return False
        if node.is_alias:
            try:
                node = node.final_target
            except (griffe.AliasResolutionError, griffe.CyclicAliasError):
                return False
    return True


class SphinxRoles(griffe.Extension):
    """Rewrite the Sphinx roles of every docstring once the package is loaded."""

    def on_package(self, *, pkg: griffe.Module, **kwargs: Any) -> None:
        for obj in _objects(pkg):
            if obj.docstring is not None and ":" in obj.docstring.value:
                obj.docstring.value = convert(obj, obj.docstring.value)


def is_deprecated(obj: griffe.Object) -> bool:
    """Whether ``obj`` is a deprecated alias: its docstring starts with "Deprecated"."""
    return obj.docstring is not None and obj.docstring.value.lstrip().startswith("Deprecated")


class HideDeprecated(griffe.Extension):
    """Leave deprecated aliases out of the API pages (see the module docstring)."""

    def on_package(self, *, pkg: griffe.Module, **kwargs: Any) -> None:
        for obj in list(_objects(pkg)):
            for name in [n for n, m in obj.members.items() if not m.is_alias and is_deprecated(m)]:
                del obj.members[name]
