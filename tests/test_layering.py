"""Lower layers never import higher ones (ARCHITECTURE.md): core < dem < surrogate < model < edges."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

SRC = Path(__file__).parents[1] / "src" / "msmill"
LAYER = {"dem": 1, "surrogate": 2, "model": 3, "cli": 4, "plots": 4, "report": 4, "web": 4}


def layer_of(module: str) -> int:
    """Layer of ``msmill.x.y`` (0 = core: the top-level modules)."""
    parts = module.split(".")
    return LAYER.get(parts[1], 0) if len(parts) > 1 else 0


def imported_modules(path: Path) -> set[str]:
    tree = ast.parse(path.read_text(encoding="utf-8"))
    found = set()
    for node in ast.walk(tree):  # function-level imports count too
        if isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            found.add(node.module)
        elif isinstance(node, ast.Import):
            found.update(a.name for a in node.names)
    return {m for m in found if m == "msmill" or m.startswith("msmill.")}


FILES = sorted(p for p in SRC.rglob("*.py") if p.name not in {"__main__.py"})


@pytest.mark.parametrize("path", FILES, ids=lambda p: str(p.relative_to(SRC)))
def test_no_upward_imports(path):
    rel = path.relative_to(SRC).with_suffix("")
    own = "msmill." + ".".join(p for p in rel.parts if p != "__init__")
    mine = layer_of(own)
    upward = sorted(m for m in imported_modules(path) if layer_of(m) > mine)
    assert not upward, f"{own} (layer {mine}) imports higher layers: {upward}"


def test_layer_map_sees_the_packages():
    # guards the test itself: every sub-package is mapped, so nothing is silently "core"
    packages = {p.name for p in SRC.iterdir() if p.is_dir() and (p / "__init__.py").exists()}
    assert packages - set(LAYER) <= set(), packages - set(LAYER)
