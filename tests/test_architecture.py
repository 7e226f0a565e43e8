"""The layer rule of docs/architecture.md, read from the source: every import of a mpcmobo
module (at module level or inside a function) points to the same layer or one before it in

    systems -> mpc -> identify -> rl -> bo -> learners -> experiment -> connect -> plots -> cli

so the package has no back-references and no import cycle between layers."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

import mpcmobo

PACKAGE = Path(mpcmobo.__file__).parent
LAYERS = [
    "systems",
    "mpc",
    "identify",
    "rl",
    "bo",
    "learners",
    "experiment",
    "connect",
    "plots",
    "cli",
]
RANK = {name: i for i, name in enumerate(LAYERS)}


def _layer(module: str) -> str | None:
    parts = module.split(".")
    return parts[1] if len(parts) > 1 and parts[0] == "mpcmobo" and parts[1] in RANK else None


def _imports(path: Path) -> list[tuple[int, str]]:
    """(line, module) of every mpcmobo import in the file, lazy ones included."""
    found = []
    for node in ast.walk(ast.parse(path.read_text(), filename=str(path))):
        if isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            found.append((node.lineno, node.module))
            found += [(node.lineno, f"{node.module}.{a.name}") for a in node.names]
        elif isinstance(node, ast.Import):
            found += [(node.lineno, a.name) for a in node.names]
    return found


def _edges() -> list[tuple[str, str, int, str]]:
    """(importing layer, imported layer, line, file) for every cross-module import."""
    edges = set()
    for path in sorted(PACKAGE.rglob("*.py")):
        rel = path.relative_to(PACKAGE.parent)
        src = _layer(".".join(rel.with_suffix("").parts))
        if src is None:
            continue
        for line, module in _imports(path):
            dst = _layer(module)
            if dst is not None and dst != src:
                edges.add((src, dst, line, str(rel)))
    return sorted(edges)


def test_every_import_points_down_the_pipeline():
    edges = _edges()
    assert edges, "no mpcmobo imports found: the test reads the wrong files"
    upward = [f"{f}:{line} ({src} imports {dst})" for src, dst, line, f in edges
              if RANK[dst] >= RANK[src]]  # fmt: skip
    assert not upward, "imports against the layer order:\n" + "\n".join(upward)


def test_the_rule_catches_a_back_reference(tmp_path, monkeypatch):
    """The checker itself: a lazy import of mpc inside systems is reported."""
    pkg = tmp_path / "mpcmobo"
    (pkg / "systems").mkdir(parents=True)
    (pkg / "systems" / "base.py").write_text(
        "def make():\n    from mpcmobo.mpc.parametric import ParametricMPC\n    return ParametricMPC\n"
    )
    monkeypatch.setattr(__import__(__name__), "PACKAGE", pkg)
    with pytest.raises(AssertionError, match="systems imports mpc"):
        test_every_import_points_down_the_pipeline()
