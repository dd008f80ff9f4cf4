"""The package's layering: a module imports only from its own layer or layers to its left."""

import ast
from pathlib import Path

from script_support import load_script

PKG = Path(__file__).resolve().parents[1] / "torchfilt"
#: scripts/house_metrics.py: the built-in error classes and the function length, counted as the
#: closing figures count them
METRICS = load_script("house_metrics")

#: numerics/optim -> cubature -> models -> filters -> systems/dmc -> io -> training/plots -> pipeline -> cli
LAYERS = {
    "_version": 0,
    "exceptions": 0,
    "settings": 0,
    "numerics": 1,
    "optim": 1,
    "cubature": 2,
    "models": 3,
    "filters": 4,
    "systems": 5,
    "estimators": 5,
    "dmc": 5,
    "io": 6,
    "training": 7,
    "plots": 7,
    "pipeline": 8,
    "cli": 9,
    "__init__": 10,
    "__main__": 10,
}


def layer_of(module: str) -> int:
    parts = module.split(".")
    head = parts[1] if len(parts) > 1 else "__init__"
    head = head.removesuffix(".py")
    assert head in LAYERS, f"{module}: unknown layer {head!r}; add it to LAYERS"
    return LAYERS[head]


def test_no_upward_imports():
    bad = []
    for path in PKG.rglob("*.py"):
        rel = path.relative_to(PKG.parent).with_suffix("")
        module = ".".join(rel.parts)
        if module.endswith(".__init__") and module.count(".") == 1:
            module = "torchfilt"
        own = layer_of(module) if module != "torchfilt" else LAYERS["__init__"]
        for node in ast.walk(ast.parse(path.read_text())):
            names = []
            if isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
                names = [node.module]
            elif isinstance(node, ast.Import):
                names = [a.name for a in node.names]
            for name in names:
                if name == "torchfilt" or not name.startswith("torchfilt."):
                    if name == "torchfilt" and own < LAYERS["__init__"]:
                        bad.append(f"{module} imports the top-level package")
                    continue
                if layer_of(name) > own:
                    bad.append(f"{module} (layer {own}) imports {name} (layer {layer_of(name)})")
    assert not bad, "\n".join(bad)


def _modules() -> dict[str, Path]:
    """Every module of the package by dotted name (a package by its ``__init__``)."""
    out = {}
    for path in PKG.rglob("*.py"):
        parts = path.relative_to(PKG.parent).with_suffix("").parts
        if parts[-1] == "__init__":
            parts = parts[:-1]
        out[".".join(parts)] = path
    return out


def _imports(path: Path, modules: dict[str, Path]) -> list[tuple[str, str]]:
    """``(module, name)`` for every ``torchfilt`` import anywhere in the file (inside functions and
    ``TYPE_CHECKING`` blocks too): ``name`` is the imported attribute, or ``""`` for a module."""
    out = []
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            for a in node.names:
                sub = f"{node.module}.{a.name}"
                out.append((sub, "") if sub in modules else (node.module, a.name))
        elif isinstance(node, ast.Import):
            out.extend((a.name, "") for a in node.names)
    return [(m, n) for m, n in out if m == "torchfilt" or m.startswith("torchfilt.")]


def _package(module: str, modules: dict[str, Path]) -> str:
    """The sub-package a module belongs to: ``torchfilt.filters`` for ``torchfilt.filters.x``."""
    parts = module.split(".")
    return ".".join(parts[:2]) if len(parts) > 1 else module


def test_no_import_cycles():
    """No module imports, directly or through others, a module that imports it back (imports
    inside functions and ``TYPE_CHECKING`` blocks count: they hide a cycle, they do not remove it).
    Edges into a package's own ``__init__`` from its submodules are not counted when the
    ``__init__`` only re-exports (the usual layout); every other cycle is."""
    modules = _modules()
    graph: dict[str, set[str]] = {m: set() for m in modules}
    for mod, path in modules.items():
        for target, _ in _imports(path, modules):
            if target not in modules or target == mod:
                continue
            if mod.startswith(target + "."):
                continue  # a submodule reading its package's re-exports
            if target.startswith(mod + ".") and modules[mod].name == "__init__.py":
                continue  # a package re-exporting its submodules
            graph[mod].add(target)
    # Tarjan's strongly connected components
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on: set[str] = set()
    cycles: list[list[str]] = []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        on.add(v)
        for w in graph[v]:
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                on.discard(w)
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                cycles.append(sorted(comp))

    for v in graph:
        if v not in index:
            visit(v)
    assert not cycles, "import cycles:\n" + "\n".join(" <-> ".join(c) for c in cycles)


def test_no_private_imports_across_packages():
    """A name or module starting with ``_`` is private to its sub-package (``torchfilt.filters``,
    ``torchfilt.numerics``, ...): no other sub-package imports it."""
    modules = _modules()
    bad = []
    for mod, path in modules.items():
        own = _package(mod, modules)
        for target, name in _imports(path, modules):
            if _package(target, modules) == own:
                continue
            private_module = any(
                p.startswith("_") and not p.startswith("__") for p in target.split(".")
            )
            if (name.startswith("_") and not name.startswith("__")) or (
                private_module and target != "torchfilt._version"
            ):
                bad.append(f"{mod} imports {target}{'.' + name if name else ''}")
    assert not bad, "\n".join(bad)


#: A ``raise`` in the package must not use a built-in exception class (METRICS.BUILTIN_ERRORS)
#: for a user error: every user error is a ``TorchfiltError`` subclass (which may also derive
#: from one of these).
#: The comment that marks a raise of a built-in as a genuine internal-bug check.
INTERNAL_MARK = "# internal: not a user error"


def _builtin_raises(path: Path) -> list[str]:
    lines = path.read_text().splitlines()
    out = []
    for node in ast.walk(ast.parse("\n".join(lines))):
        if not isinstance(node, ast.Raise):
            continue
        name = METRICS.raised_name(node)
        if name in METRICS.BUILTIN_ERRORS and INTERNAL_MARK not in lines[node.lineno - 1]:
            out.append(f"{node.lineno}: raise {name}")
    return out


def test_no_builtin_raises():
    bad = []
    for path in sorted(PKG.rglob("*.py")):
        rel = path.relative_to(PKG).as_posix()
        bad += [f"torchfilt/{rel}:{where}" for where in _builtin_raises(path)]
    assert not bad, (
        "raise a torchfilt.exceptions.TorchfiltError subclass for a user error (or mark an "
        f"internal-bug check with {INTERNAL_MARK!r}):\n" + "\n".join(bad)
    )


#: the execution modes whose choice belongs to torchfilt.filters.plan alone
EXECUTION_MODES = {
    "eager",
    "compiled-step",
    "compiled-loop",
    "compiled-chunks",
    "graphed",
    "kalman-parallel",
    "kalman-adjoint",
    "kalman-riccati",
    "kalman-fast",
    "kalman-sequential",
}
PLAN_MODULE = PKG / "filters" / "plan.py"


def _strings(node: ast.AST) -> set[str]:
    return {
        n.value for n in ast.walk(node) if isinstance(n, ast.Constant) and isinstance(n.value, str)
    }


def test_one_module_owns_the_path_decision():
    """Only filters/plan.py branches on the execution mode: no other module compares a value with
    an execution-mode string (``==``, ``in``, ``match``) or reads ``compile_mode``. The engines
    look the plan's answer up in tables; they do not decide."""
    bad = []
    for path in PKG.rglob("*.py"):
        if path == PLAN_MODULE:
            continue
        rel = path.relative_to(PKG.parent)
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.Compare):
                hit = _strings(node) & EXECUTION_MODES
                if hit:
                    bad.append(f"{rel}:{node.lineno} compares with {sorted(hit)}")
            elif isinstance(node, ast.match_case):
                hit = _strings(node.pattern) & EXECUTION_MODES
                if hit:
                    bad.append(f"{rel}:{node.pattern.lineno} matches {sorted(hit)}")
            elif (
                isinstance(node, ast.Attribute)
                and node.attr == "compile_mode"
                and isinstance(node.ctx, ast.Load)
            ):
                bad.append(f"{rel}:{node.lineno} reads compile_mode")
    assert not bad, "\n".join(bad)


def test_no_module_over_800_lines():
    bad = []
    for path in PKG.rglob("*.py"):
        lines = len(path.read_text().splitlines())
        if lines > METRICS.MODULE_LIMIT:
            bad.append(f"{path.relative_to(PKG).as_posix()}: {lines} lines")
    assert not bad, "\n".join(bad)


#: Deprecated shims that name a module of a higher layer through ``importlib`` (so that they do not
#: import it when the package loads): each re-exports names that moved up a layer, for one release.
DEPRECATED_SHIMS = {
    "torchfilt.training": {"torchfilt.pipeline"},
    "torchfilt.training.bundle": {"torchfilt.pipeline.bundle"},
    "torchfilt.training.recipe": {"torchfilt.pipeline.recipe"},
    "torchfilt.training.run": {
        "torchfilt.pipeline.run",
        "torchfilt.pipeline.run_checks",
        "torchfilt.pipeline.run_stages",
    },
}


def test_upward_references_only_in_deprecated_shims():
    """A string naming a ``torchfilt`` module of a higher layer (an ``importlib.import_module``
    target, which :func:`test_no_upward_imports` cannot see) appears only in the deprecated shims
    of :data:`DEPRECATED_SHIMS`, and only for the modules they stand in for."""
    modules = _modules()
    bad = []
    for mod, path in modules.items():
        if mod == "torchfilt":
            continue
        own = layer_of(mod)
        for node in ast.walk(ast.parse(path.read_text())):
            if not (isinstance(node, ast.Constant) and isinstance(node.value, str)):
                continue
            target = node.value
            if target not in modules or target == "torchfilt" or layer_of(target) <= own:
                continue
            if target not in DEPRECATED_SHIMS.get(mod, set()):
                bad.append(f"{mod} (layer {own}) names {target} (layer {layer_of(target)})")
    assert not bad, "\n".join(bad)


#: test files that cover the package as a whole and sit at the top of tests/
CROSS_CUTTING_TESTS = {
    "test_architecture.py",
    "test_public_api.py",
    "test_cuda.py",
    "test_docstrings.py",
}


def test_tests_mirror_the_package():
    """Each test file sits in the folder of the sub-package it tests (``tests/filters/``,
    ``tests/models/gp/``, ...; ``tests/scripts/`` for the scripts, the README and the docs), so
    a module's tests are found where the module is."""
    tests = PKG.parent / "tests"
    packages = {p.relative_to(PKG).as_posix() for p in PKG.rglob("*") if p.is_dir()}
    packages -= {"__pycache__"}
    bad = []
    for path in sorted(tests.rglob("test_*.py")):
        folder = path.parent.relative_to(tests).as_posix()
        if folder == ".":
            if path.name not in CROSS_CUTTING_TESTS:
                bad.append(
                    f"tests/{path.name}: move it into the folder of the sub-package it tests"
                )
        elif folder != "scripts" and folder not in packages:
            bad.append(f"tests/{folder}/{path.name}: torchfilt/{folder} is not a sub-package")
    assert not bad, "\n".join(bad)


#: functions allowed a body (after the docstring) over METRICS.FUNCTION_LIMIT, each with the reason;
#: the issue that set the limit allows at most three
LONG_FUNCTIONS: dict[str, str] = {}


def test_no_function_over_100_lines():
    """A function's body (its docstring not counted) stays at 100 lines or under (as
    ``scripts/house_metrics.py`` counts), except the few of LONG_FUNCTIONS with their reason."""
    assert len(LONG_FUNCTIONS) <= 3
    bad = []
    for path in sorted(PKG.rglob("*.py")):
        rel = path.relative_to(PKG).as_posix()
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef):
                n = METRICS.body_lines(node)
                if n > METRICS.FUNCTION_LIMIT and f"{rel}:{node.name}" not in LONG_FUNCTIONS:
                    bad.append(f"{rel}:{node.name}: {n} lines")
    assert not bad, "\n".join(bad)


def test_every_public_name_of_filters_is_for_users():
    """No name of ``torchfilt.filters.__all__`` exists only for the engines. The rule: none is
    defined in the engine modules (``Step``, ``OnlineStep``, the engines, ``ExecutionPlan``,
    ``TraceFailure``, ``CubatureStep`` live in ``torchfilt.filters.engine`` / ``plan`` /
    ``cubature_step``), none is a type that only the engines' ``Step`` protocol passes (named in
    its signatures but in no signature of an exported function or class), and each has a
    docstring. The records the protocol alone passes warn when reached through
    ``torchfilt.filters`` and live in their modules."""
    import inspect
    import re
    import warnings

    import pytest

    import torchfilt.filters as filters
    from torchfilt.filters import engine

    protocol = {n for n in dir(engine.OnlineStep) if not n.startswith("_")}

    def names_in_signatures(objs: list[object], skip: frozenset[str] = frozenset()) -> set[str]:
        """The identifiers in the signatures of ``objs`` and of their public methods, less the
        methods named in ``skip`` and the deprecated ones."""
        found: set[str] = set()
        for obj in objs:
            members = [obj]
            if inspect.isclass(obj):
                members += [
                    m
                    for n, m in vars(obj).items()
                    if (not n.startswith("_") or n == "__init__") and n not in skip
                ]
            for m in members:
                if (inspect.getdoc(m) or "").startswith("Deprecated"):
                    continue
                m = getattr(m, "__func__", m)
                if isinstance(m, property):
                    m = m.fget
                if not callable(m):
                    continue
                try:
                    sig = inspect.signature(m)
                except (TypeError, ValueError):
                    continue
                text = " ".join(
                    [str(p.annotation) for p in sig.parameters.values()]
                    + [str(sig.return_annotation)]
                )
                found |= set(re.findall(r"[A-Za-z_]\w*", text))
        return found

    engine_modules = {
        "torchfilt.filters.engine",
        "torchfilt.filters.plan",
        "torchfilt.filters.cubature_step",
    }
    public = [getattr(filters, name) for name in filters.__all__]
    # a public filter implements the protocol's methods (``GaussianFilter.step``): those do not
    # make the records they pass user-facing
    protocol_only = names_in_signatures([engine.Step, engine.OnlineStep]) - names_in_signatures(
        public, skip=frozenset(protocol)
    )
    for name, obj in zip(filters.__all__, public, strict=True):
        assert getattr(obj, "__module__", "") not in engine_modules, name
        assert name not in protocol_only, f"{name}: only the engines' Step protocol uses it"
        assert inspect.getdoc(obj), f"{name}: no docstring says how a user uses it"
    assert {"StepRecord", "FilterInputs"} <= protocol_only  # the rule sees them
    for name, module in (
        ("StepRecord", "torchfilt.filters.results"),
        ("FilterInputs", "torchfilt.filters.inputs"),
    ):
        with pytest.warns(DeprecationWarning, match=f"use {module}.{name}"):
            alias = getattr(filters, name)
        with warnings.catch_warnings():
            warnings.simplefilter("error")
            assert alias is getattr(__import__(module, fromlist=[name]), name)
