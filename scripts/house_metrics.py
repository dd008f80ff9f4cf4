"""The shape of the package, measured from its source: sizes, long functions, public surface.

Reads the source only (nothing is imported or run), so it can measure any checkout:

    python scripts/house_metrics.py --out out/house            # this checkout
    python scripts/house_metrics.py --root ../other-checkout   # another one

Rows: lines of the package and of the tests (non-blank lines are not distinguished: ``wc -l``
counts), the test:code ratio, modules over 800 lines, functions whose body (after the docstring)
is over 100 lines (each listed with its length), names in the top-level ``torchfilt.__all__``, and ``raise`` statements of built-in
exception classes (``ValueError``, ``TypeError``, ...) in the package.
"""

from __future__ import annotations

import argparse
import ast
import sys
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import table, write_json

BUILTIN_ERRORS = {
    "AssertionError",
    "FileNotFoundError",
    "IndexError",
    "KeyError",
    "LookupError",
    "NotImplementedError",
    "OSError",
    "RuntimeError",
    "TypeError",
    "ValueError",
}
MODULE_LIMIT = 800
FUNCTION_LIMIT = 100


def _lines(path: Path) -> int:
    return len(path.read_text().splitlines())


def body_lines(node: ast.FunctionDef | ast.AsyncFunctionDef) -> int:
    """Lines of a function's body after its docstring (the signature and docstring not counted)."""
    body = node.body
    if (
        len(body) > 1
        and isinstance(body[0], ast.Expr)
        and isinstance(body[0].value, ast.Constant)
        and isinstance(body[0].value.value, str)
    ):
        body = body[1:]
    return (node.end_lineno or node.lineno) - body[0].lineno + 1


def raised_name(node: ast.Raise) -> str | None:
    """The name of the class a ``raise`` statement raises (``raise X`` or ``raise X(...)``)."""
    exc = node.exc
    if isinstance(exc, ast.Call):
        exc = exc.func
    return exc.id if isinstance(exc, ast.Name) else None


def measure(root: Path) -> dict[str, Any]:
    """The figures of the checkout at ``root`` (its ``torchfilt/`` and ``tests/`` folders)."""
    pkg, tests = root / "torchfilt", root / "tests"
    modules = sorted(pkg.rglob("*.py"))
    code = sum(_lines(p) for p in modules)
    test_lines = sum(_lines(p) for p in tests.rglob("*.py"))
    big = {str(p.relative_to(root)): _lines(p) for p in modules if _lines(p) > MODULE_LIMIT}
    long_functions: dict[str, int] = {}
    raises: dict[str, int] = {}
    for path in modules:
        tree = ast.parse(path.read_text())
        rel = str(path.relative_to(root))
        for node in ast.walk(tree):
            if isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef):
                length = body_lines(node)
                if length > FUNCTION_LIMIT:
                    long_functions[f"{rel}:{node.name}"] = length
            elif isinstance(node, ast.Raise) and raised_name(node) in BUILTIN_ERRORS:
                raises[rel] = raises.get(rel, 0) + 1
    top = _top_level_names(pkg / "__init__.py")
    return {
        "package_lines": code,
        "test_lines": test_lines,
        "test_code_ratio": round(test_lines / code, 3),
        "modules_over_800": big,
        "functions_over_100": dict(sorted(long_functions.items(), key=lambda kv: -kv[1])),
        "top_level_names": len(top),
        "builtin_raises": sum(raises.values()),
        "builtin_raises_by_module": raises,
        "test_files": len(list(tests.rglob("test_*.py"))),
        "test_folders": len({p.parent for p in tests.rglob("test_*.py")}),
    }


def _top_level_names(init: Path) -> list[str]:
    for node in ast.parse(init.read_text()).body:
        if isinstance(node, ast.Assign) and any(
            isinstance(t, ast.Name) and t.id == "__all__" for t in node.targets
        ):
            return [ast.literal_eval(e) for e in node.value.elts]  # type: ignore[attr-defined]
    return []


def main() -> None:
    ap = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("--root", type=Path, default=Path(__file__).resolve().parents[1])
    ap.add_argument("--out", type=Path, default=None, help="folder for house_metrics.json")
    args = ap.parse_args()
    m = measure(args.root.resolve())
    rows = [
        ["package lines", m["package_lines"]],
        ["test lines", m["test_lines"]],
        ["test:code", m["test_code_ratio"]],
        ["test files (folders)", f"{m['test_files']} ({m['test_folders']})"],
        [f"modules over {MODULE_LIMIT} lines", len(m["modules_over_800"])],
        [f"functions over {FUNCTION_LIMIT} lines", len(m["functions_over_100"])],
        ["top-level names (__all__)", m["top_level_names"]],
        ["raises of built-in exceptions", m["builtin_raises"]],
    ]
    print(table(["measure", "value"], rows))
    for title, items in (
        (f"modules over {MODULE_LIMIT} lines", m["modules_over_800"]),
        (f"functions over {FUNCTION_LIMIT} lines", m["functions_over_100"]),
    ):
        if items:
            print(f"\n{title}:")
            for name, n in items.items():
                print(f"  {n:5d}  {name}")
    if args.out is not None:
        write_json(args.out / "house_metrics.json", m)


if __name__ == "__main__":
    main()
