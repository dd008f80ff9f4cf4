"""Regenerate the generated documentation: ``docs/recipes.md`` from the recipe schema.

python scripts/make_docs.py
"""

from __future__ import annotations

from pathlib import Path

from torchfilt.io import atomic_write_text
from torchfilt.pipeline.recipe import recipe_reference

ROOT = Path(__file__).resolve().parents[1]


def main() -> int:
    path = atomic_write_text(ROOT / "docs" / "recipes.md", recipe_reference())
    print(f"wrote {path}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
