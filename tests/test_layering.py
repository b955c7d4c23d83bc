"""Lower layers never import higher ones, nor a sibling package (ARCHITECTURE.md):

core < {dem, surrogate} < {pipeline, model} < edges. ``dem`` and ``surrogate`` never import each other;
nor do ``pipeline`` (store, campaigns) and ``model`` (the semi-analytical mill). The edges (cli, plots,
report, web) may import each other.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

SRC = Path(__file__).parents[1] / "src" / "msmill"
LAYER = {"dem": 1, "surrogate": 1, "pipeline": 2, "model": 2, "cli": 3, "plots": 3, "report": 3, "web": 3}
EDGES = 3


def package_of(module: str) -> str | None:
    """Sub-package of ``msmill.x.y`` (None for core)."""
    parts = module.split(".")
    return parts[1] if len(parts) > 1 and parts[1] in LAYER else None


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
    if 0 < mine < EDGES:
        pkg = package_of(own)
        sideways = sorted(m for m in imported_modules(path)
                          if layer_of(m) == mine and package_of(m) not in (None, pkg))
        assert not sideways, f"{own} imports its sibling package (layer {mine}): {sideways}"


def test_layer_map_sees_the_packages():
    # guards the test itself: every sub-package is mapped, so nothing is silently "core"
    packages = {p.name for p in SRC.iterdir() if p.is_dir() and (p / "__init__.py").exists()}
    assert packages - set(LAYER) <= set(), packages - set(LAYER)
