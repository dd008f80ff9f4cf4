"""The package's layering: a module imports only from its own layer or layers to its left."""

import ast
from pathlib import Path

PKG = Path(__file__).resolve().parents[1] / "torchfilt"

#: numerics -> cubature -> models -> filters -> systems/dmc -> io -> training/plots -> pipeline -> cli
LAYERS = {
    "_version": 0,
    "exceptions": 0,
    "numerics": 1,
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
