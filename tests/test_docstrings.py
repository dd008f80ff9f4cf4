"""Every public name has an API page entry that states its shapes and its errors.

The API pages (mkdocs.yml, mkdocstrings) are rendered from the docstrings, in Google style. The
public names are the ``__all__`` of each sub-package in :data:`PACKAGES`. For each of them, read
statically with griffe (as the docs build reads them):

* every public class, function, public method of a public class (no leading underscore; a
  deprecated alias, whose docstring starts with "Deprecated", is exempt) and property has a
  docstring;
* every ``Tensor`` argument (annotation mentioning ``Tensor``) of a function, method or constructor
  has an ``Args:`` entry that gives its shape in the ``(..., T, n)`` notation: a double-backquoted
  parenthesised shape (``(..., T, n)``, ``(n, n)``, ``(...)``) or the word "scalar". A return
  annotation mentioning ``Tensor`` k times needs at least k shapes in ``Returns:`` (``Yields:``
  for a generator); a property, or a method without arguments, may give them in its summary
  instead. Tensors inside a ``Callable[...]`` annotation are not arguments and do not count; a
  tensor whose shape is free is documented as "any shape";
* a result container (NamedTuple or dataclass) gives each ``Tensor`` field's shape in its
  ``Attributes:`` section;
* each ``Args:`` entry documents exactly one parameter of the signature (``x0, P0: ...`` is two
  parameters on one line, which the Google parser cannot split), and griffe's Google parser
  raises no warning on the docstring;
* a function that raises a :class:`~torchfilt.exceptions.TorchfiltError` subclass itself or
  through the package's own checks has a ``Raises:`` section that names each such class (or a
  base class of it). The analysis is static and deliberately simple (:func:`raised_errors`): a
  ``raise E(...)`` / ``raise E`` in the function's own source (nested functions included), plus
  the errors of each *checking helper* it calls. A checking helper is a function or method of the
  package whose name starts with ``check_``, ``_check``, ``_validate`` or ``_require``; its
  errors are its own raises and, transitively, those of the checking helpers it calls. Errors a
  function meets only through other (non-checking) calls are not counted, so a function that
  raises nothing of its own needs no ``Raises:`` section.

A method without a docstring that overrides a documented method of a base class is held to the
base's docstring (what ``help()`` shows), checked against its own signature.

The names in :data:`PENDING` are the offenders left in files other work is editing; the test fails
for an offender not listed there and for a listed name that no longer offends, so the set only
shrinks.
"""

from __future__ import annotations

import ast
import importlib
import inspect
import logging
import re
import textwrap
from collections.abc import Iterator
from functools import cache
from pathlib import Path

import pytest

import torchfilt.exceptions

griffe = pytest.importorskip("griffe")

ROOT = Path(__file__).resolve().parents[1]

#: The packages whose ``__all__`` makes the public names.
PACKAGES = (
    "torchfilt",
    "torchfilt.filters",
    "torchfilt.models",
    "torchfilt.models.gp",
    "torchfilt.cubature",
    "torchfilt.numerics",
    "torchfilt.optim",
    "torchfilt.training",
    "torchfilt.pipeline",
    "torchfilt.io",
    "torchfilt.systems",
    "torchfilt.dmc",
    "torchfilt.exceptions",
    "torchfilt.settings",
    "torchfilt.plots",
)

#: Offenders in the files being edited in parallel (filters other than metrics.py, training,
#: optim, models.gp, models/inducing.py, pipeline). Empty now: every public name follows the rule;
#: never add one.
PENDING: set[str] = set()

#: A shape in the ``(..., T, n)`` notation: ````(..., T, n)````, ````(n, n)````, ````(...)````, the
#: word "scalar", or "any shape" (a tensor whose shape the function does not constrain).
SHAPE = re.compile(r"``\([^`]*\)``|\bscalar\b|\bany\s+shape\b", re.IGNORECASE)
#: griffe's warning for an Args entry not in the signature: reported by :func:`check_arguments`.
UNKNOWN = "does not appear in the"
#: The name prefixes of the package's checking helpers (see the module docstring).
CHECKER_PREFIXES = ("check_", "_check", "_validate", "_require")
#: The error classes: every TorchfiltError subclass of torchfilt.exceptions, by name.
ERRORS = {
    name: value
    for name, value in vars(torchfilt.exceptions).items()
    if isinstance(value, type) and issubclass(value, torchfilt.exceptions.TorchfiltError)
}


# ------------------------------------------------------------------------------------- loading
@cache
def package() -> griffe.Module:
    return griffe.load("torchfilt", search_paths=[str(ROOT)])


def public_objects() -> dict[str, griffe.Object]:
    """Each public class and function by its canonical path (where it is defined)."""
    found: dict[str, griffe.Object] = {}
    pkg = package()
    for name in PACKAGES:
        module = importlib.import_module(name)
        for public in module.__all__:
            value = getattr(module, public)
            if not (inspect.isclass(value) or inspect.isfunction(value)):
                continue  # a module or a constant
            path = f"{value.__module__}.{value.__qualname__}"
            found[path] = pkg[path.removeprefix("torchfilt.")]
    return found


# ------------------------------------------------------------------------------------ docstrings
def parse(obj: griffe.Object) -> tuple[list[griffe.DocstringSection], list[str]]:
    """The Google sections of ``obj``'s docstring, and the warnings griffe's parser logs."""
    if obj.docstring is None:
        return [], []
    messages: list[str] = []

    class Collect(logging.Handler):
        def emit(self, record: logging.LogRecord) -> None:
            messages.append(record.getMessage().split(": ", 1)[-1])

    handler = Collect(logging.WARNING)
    log = logging.getLogger("griffe")
    log.addHandler(handler)
    try:
        sections = obj.docstring.parse("google", returns_multiple_items=False)
    finally:
        log.removeHandler(handler)
    return sections, messages


def section(sections: list[griffe.DocstringSection], kind: str) -> list[griffe.DocstringSection]:
    return [s for s in sections if s.kind.value == kind]


def entries(sections: list[griffe.DocstringSection], kind: str) -> dict[str, str]:
    """Name -> description of the entries of every ``kind`` section."""
    return {item.name: item.description for s in section(sections, kind) for item in s.value}


def text_of(sections: list[griffe.DocstringSection], kind: str) -> str:
    parts: list[str] = []
    for s in section(sections, kind):
        for item in s.value:
            parts.append(f"{item.annotation or ''} {item.description}")
    return "\n".join(parts)


def mentions_tensor(annotation: object) -> int:
    """How many tensors an annotation holds (those inside a ``Callable[...]`` do not count)."""
    if annotation is None:
        return 0
    text = str(annotation)
    while (start := text.find("Callable[")) >= 0:
        depth, end = 0, start + len("Callable")
        for end in range(start + len("Callable"), len(text)):
            depth += {"[": 1, "]": -1}.get(text[end], 0)
            if depth == 0:
                break
        text = text[:start] + text[end + 1 :]
    return len(re.findall(r"\bTensor\b", text))


def is_deprecated(obj: griffe.Object) -> bool:
    return obj.docstring is not None and obj.docstring.value.startswith("Deprecated")


# ---------------------------------------------------------------------------------------- raises
def _called_names(tree: ast.AST) -> Iterator[str]:
    for node in ast.walk(tree):
        if isinstance(node, ast.Call):
            if isinstance(node.func, ast.Name):
                yield node.func.id
            elif isinstance(node.func, ast.Attribute):
                yield node.func.attr


def _own_raises(tree: ast.AST) -> set[str]:
    raised: set[str] = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Raise) and node.exc is not None:
            exc = node.exc.func if isinstance(node.exc, ast.Call) else node.exc
            name = exc.id if isinstance(exc, ast.Name) else getattr(exc, "attr", None)
            if name in ERRORS:
                raised.add(name)
    return raised


def _tree(obj: griffe.Object) -> ast.AST:
    return ast.parse(textwrap.dedent(obj.source))


def _functions(obj: griffe.Object) -> Iterator[griffe.Function]:
    for member in obj.members.values():
        if member.is_alias:
            continue
        if member.is_function:
            yield member
        elif member.is_class or member.is_module:
            yield from _functions(member)


@cache
def checkers() -> dict[str, set[str]]:
    """Path -> errors of each of the package's checking helpers (transitively)."""
    helpers = {f.path: f for f in _functions(package()) if f.name.startswith(CHECKER_PREFIXES)}
    raised = {path: _own_raises(_tree(f)) for path, f in helpers.items()}
    calls = {
        path: _resolve(f.module, _called_names(_tree(f))) - {path} for path, f in helpers.items()
    }
    changed = True
    while changed:
        changed = False
        for path, called in calls.items():
            for other in called:
                if not raised[other] <= raised[path]:
                    raised[path] |= raised[other]
                    changed = True
    return raised


def _resolve(module: griffe.Module, names: Iterator[str]) -> set[str]:
    """The checking helpers that calls to ``names`` from ``module`` reach: the module's own helper
    of that name, else the one it imports under that name, else every helper of that name (a
    method called on ``self`` or another object)."""
    helpers = _helper_paths()
    found: set[str] = set()
    for name in names:
        if not name.startswith(CHECKER_PREFIXES):
            continue
        own = {p for p in helpers.get(name, ()) if p.startswith(f"{module.path}.")}
        member = module.members.get(name)
        if own:
            found |= own
        elif member is not None and member.is_alias and member.target_path in helpers.get(name, ()):
            found.add(member.target_path)
        else:
            found |= helpers.get(name, set())
    return found


@cache
def _helper_paths() -> dict[str, set[str]]:
    names: dict[str, set[str]] = {}
    for f in _functions(package()):
        if f.name.startswith(CHECKER_PREFIXES):
            names.setdefault(f.name, set()).add(f.path)
    return names


def raised_errors(func: griffe.Function) -> set[str]:
    """The TorchfiltError classes ``func`` raises itself or through a checking helper."""
    tree = _tree(func)
    errors = _own_raises(tree)
    known = checkers()
    for path in _resolve(func.module, _called_names(tree)):
        errors |= known[path]
    return errors


def _documents(raised: str, documented: set[str]) -> bool:
    """Whether ``raised`` or one of its base classes is named in ``documented``."""
    return any(base.__name__ in documented for base in ERRORS[raised].__mro__)


def raises_section(sections: list[griffe.DocstringSection]) -> set[str]:
    names: set[str] = set()
    for s in section(sections, "raises"):
        for item in s.value:
            names.update(re.findall(r"\w+", str(item.annotation)))
    return names


# ----------------------------------------------------------------------------------------- rules
def _base_docstring(cls: griffe.Class, name: str) -> griffe.Object | None:
    """The first documented ``name`` along ``cls``'s bases."""
    for base in cls.mro():
        member = base.members.get(name)
        if member is not None and member.docstring is not None:
            return member
    return None


def check_arguments(
    sections: list[griffe.DocstringSection], func: griffe.Function, where: str
) -> list[str]:
    """The ``Args:`` rules: one known parameter per entry, each Tensor argument with its shape.
    ``where`` prefixes each problem (``"constructor"``), if given."""
    at = f"{where}: " if where else ""
    problems: list[str] = []
    params = {p.name: p for p in func.parameters if p.name not in ("self", "cls")}
    documented = entries(sections, "parameters")
    for name in documented:
        if name.lstrip("*") not in params:
            problems.append(f"{at}Args entry {name!r} is not one parameter of the signature")
    for name, param in params.items():
        if not mentions_tensor(param.annotation):
            continue
        described = documented.get(name, documented.get(f"*{name}", documented.get(f"**{name}")))
        if described is None:
            problems.append(f"{at}Tensor argument {name!r} has no Args entry")
        elif not SHAPE.search(described):
            problems.append(f"{at}Tensor argument {name!r} states no shape")
    return problems


def check_function(func: griffe.Function, owner: griffe.Class | None = None) -> list[str]:
    """Problems of a function or method's docstring (empty when it follows the rule)."""
    documented: griffe.Object | None = func
    if func.docstring is None and owner is not None:
        documented = _base_docstring(owner, func.name)
    if documented is None or documented.docstring is None:
        return ["no docstring"]
    sections, warnings = parse(documented)
    problems = [f"docstring warning: {w}" for w in warnings if UNKNOWN not in w]
    problems += check_arguments(sections, func, "")
    returned = mentions_tensor(func.returns)
    if returned:
        text = text_of(sections, "returns") + text_of(sections, "yields")
        if not text.strip() and not [p for p in func.parameters if p.name not in ("self", "cls")]:
            text = documented.docstring.value  # no arguments: a one-line docstring, as a property
        if not text.strip():
            problems.append("returns a Tensor but has no Returns section")
        elif len(SHAPE.findall(text)) < returned:
            problems.append(f"Returns states fewer shapes than the {returned} Tensor(s) returned")
    raised = raised_errors(func)
    named = raises_section(sections)
    missing = sorted(e for e in raised if not _documents(e, named))
    if missing:
        problems.append(f"raises {', '.join(missing)} without naming it under Raises")
    return problems


def check_property(prop: griffe.Attribute, owner: griffe.Class) -> list[str]:
    """Problems of a property's docstring: it has one, stating the shape of a Tensor value."""
    documented = prop if prop.docstring is not None else _base_docstring(owner, prop.name)
    if documented is None or documented.docstring is None:
        return ["no docstring"]
    if mentions_tensor(prop.annotation) and not SHAPE.search(documented.docstring.value):
        return ["property holding a Tensor states no shape"]
    return []


def _fields(cls: griffe.Class) -> dict[str, griffe.Attribute]:
    return {
        name: member
        for name, member in cls.members.items()
        if member.is_attribute
        and not member.is_alias
        and not name.startswith("_")
        and "property" not in member.labels
        and member.annotation is not None
        and "ClassVar" not in str(member.annotation)
    }


def is_container(cls: griffe.Class) -> bool:
    return "dataclass" in cls.labels or any("NamedTuple" in str(b) for b in cls.bases)


def check_class(cls: griffe.Class) -> dict[str, list[str]]:
    """Problems of a class and of its public methods, by qualified name."""
    found: dict[str, list[str]] = {}
    root = f"{cls.module.package.path}."  # members inherited from outside the package are not ours
    if cls.docstring is None:
        found[cls.path] = ["no docstring"]
        return found
    sections, warnings = parse(cls)
    problems = [f"docstring warning: {w}" for w in warnings if UNKNOWN not in w]
    init = cls.all_members.get("__init__")
    init = init.final_target if init is not None and init.is_alias else init
    if is_container(cls):
        attributes = entries(sections, "attributes") | entries(sections, "parameters")
        for name, field in _fields(cls).items():
            if not mentions_tensor(field.annotation):
                continue
            described = attributes.get(name) or (field.docstring and field.docstring.value)
            if not described:
                problems.append(f"Tensor field {name!r} has no Attributes entry")
            elif not SHAPE.search(described):
                problems.append(f"Tensor field {name!r} states no shape")
        post_init = cls.members.get("__post_init__")
        raised = raised_errors(post_init) if post_init is not None else set()
    elif init is not None and init.is_function and init.path.startswith(root):
        init_sections, init_warnings = parse(init) if init.docstring else ([], [])
        problems += [f"__init__ docstring warning: {w}" for w in init_warnings if UNKNOWN not in w]
        problems += check_arguments(sections + init_sections, init, "constructor")
        sections = sections + init_sections
        raised = raised_errors(init)
    else:
        raised = set()
    named = raises_section(sections)
    missing = sorted(e for e in raised if not _documents(e, named))
    if missing:
        problems.append(f"constructor raises {', '.join(missing)} without naming it under Raises")
    if problems:
        found[cls.path] = problems
    for name, member in cls.all_members.items():
        target = member.final_target if member.is_alias else member
        if name.startswith("_") or is_deprecated(target) or not target.path.startswith(root):
            continue
        if target.is_function:
            method_problems = check_function(target, cls)
        elif target.is_attribute and "property" in target.labels:
            method_problems = check_property(target, cls)
        else:
            continue
        if method_problems:
            found[target.path] = method_problems
    return found


def offenders() -> dict[str, list[str]]:
    """Every public name that breaks the rule, with what is wrong."""
    found: dict[str, list[str]] = {}
    for path, obj in sorted(public_objects().items()):
        if obj.is_class:
            found.update(check_class(obj))
        elif obj.is_function and not is_deprecated(obj):
            problems = check_function(obj)
            if problems:
                found[path] = problems
    return found


# ----------------------------------------------------------------------------------------- tests
#: The modules the parallel work edits: the only ones PENDING may name.
PENDING_MODULES = (
    "torchfilt.filters.",
    "torchfilt.training.",
    "torchfilt.optim.",
    "torchfilt.models.gp.",
    "torchfilt.models.inducing.",
    "torchfilt.pipeline.",
)


def test_pending_names_only_files_of_the_parallel_work():
    outside = sorted(
        name
        for name in PENDING
        if not name.startswith(PENDING_MODULES) or name.startswith("torchfilt.filters.metrics.")
    )
    assert not outside


def test_every_public_name_documents_its_shapes_and_errors():
    found = offenders()
    new = {name: found[name] for name in sorted(found.keys() - PENDING)}
    fixed = sorted(PENDING - found.keys())
    report = "\n".join(f"{name}: {'; '.join(problems)}" for name, problems in new.items())
    assert not new, f"{len(new)} public names break the docstring rule:\n{report}"
    assert not fixed, f"follow the rule now; remove them from PENDING: {fixed}"


SAMPLE = '''
from typing import NamedTuple
from torch import Tensor
from torchfilt.exceptions import InputError, ShapeError

class Result(NamedTuple):
    \"\"\"A result.

    Attributes:
        mean: the means, shape ``(..., T, n)``.
        cov: the covariances.
    \"\"\"

    mean: Tensor
    cov: Tensor
    var: Tensor

class Holder:
    \"\"\"Holds a tensor.\"\"\"

    @property
    def value(self) -> Tensor:
        \"\"\"The value.\"\"\"
        return self._value

    def helper(self) -> None:
        return None

def _check_x(x):
    if x is None:
        raise ShapeError("x")

def grouped(x0: Tensor, P0: Tensor) -> Tensor:
    """Grouped.

    Args:
        x0, P0: the prior, shapes ``(..., n)`` and ``(..., n, n)``.

    Returns:
        the mean, shape ``(..., n)``.
    """
    return x0

def shapeless(x: Tensor) -> tuple[Tensor, Tensor]:
    """No shapes.

    Args:
        x: the states.

    Returns:
        the mean and its covariance, shape ``(..., n)``.
    """
    return x, x

def unnamed(x: Tensor) -> None:
    """Raises without saying so.

    Args:
        x: the states, shape ``(..., T, n)``.
    """
    _check_x(x)
    if x.ndim == 0:
        raise InputError("x")

def fine(x: Tensor, n: int) -> Tensor:
    """Follows the rule.

    Args:
        x: the states, shape ``(..., T, n)``.
        n: a size.

    Returns:
        the states, shape ``(..., T, n)``.

    Raises:
        InputError: when ``x`` is bad (ShapeError is an InputError).
    """
    _check_x(x)
    return x
'''


def test_the_rule_catches_each_kind_of_offence():
    """The checker can fail: grouped Args, missing shapes, unnamed raises are each reported."""
    with griffe.temporary_visited_module(SAMPLE) as module:
        grouped = check_function(module["grouped"])
        assert any("'x0, P0' is not one parameter" in p for p in grouped)
        assert any("'x0' has no Args entry" in p for p in grouped)
        shapeless = check_function(module["shapeless"])
        assert "Tensor argument 'x' states no shape" in shapeless
        assert any("fewer shapes than the 2" in p for p in shapeless)
        assert raised_errors(module["unnamed"]) == {"InputError"}
        assert any("raises InputError without" in p for p in check_function(module["unnamed"]))
        assert check_function(module["fine"]) == []
        result = check_class(module["Result"])["module.Result"]
        assert result == [
            "Tensor field 'cov' states no shape",
            "Tensor field 'var' has no Attributes entry",
        ]
        holder = check_class(module["Holder"])
        assert holder == {
            "module.Holder.value": ["property holding a Tensor states no shape"],
            "module.Holder.helper": ["no docstring"],
        }


def test_raised_errors_follow_the_package_checks():
    """A call to a checking helper counts as raising what the helper raises, transitively."""
    pkg = package()
    assert checkers()["torchfilt.numerics.dtypes.check_real_tensor"] == {"InputTypeError"}
    assert "ShapeError" in raised_errors(pkg["filters.metrics.rmse"])  # through _check_pair
    assert raised_errors(pkg["numerics.linalg.symmetrize"]) == set()
