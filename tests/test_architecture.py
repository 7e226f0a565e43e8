"""The layer rule of docs/architecture.md, read from the source: every import of a mpcmobo
module (at module level or inside a function) points to the same layer or one before it in

    systems -> mpc -> identify -> rl -> bo -> learners -> experiment -> plots -> dashboard -> cli

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
    "plots",
    "dashboard",
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
    upward = [
        f"{f}:{line} ({src} imports {dst})" for src, dst, line, f in edges if RANK[dst] >= RANK[src]
    ]
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


def _module_imports(package: Path, sub: str) -> dict[str, set[str]]:
    """For each module of ``mpcmobo.<sub>``, the modules of ``mpcmobo.<sub>`` it imports,
    lazy and type-only imports (under ``TYPE_CHECKING``) included."""
    graph: dict[str, set[str]] = {}
    prefix = f"mpcmobo.{sub}."
    for path in sorted((package / sub).glob("*.py")):
        name = f"{prefix}{path.stem}"
        graph[name] = set()
        for _, module in _imports(path):
            for candidate in (module, module.rsplit(".", 1)[0]):
                if candidate.startswith(prefix) and candidate.count(".") == 2:
                    graph[name].add(candidate)
                    break
        graph[name].discard(name)
    return graph


def _cycle(graph: dict[str, set[str]]) -> list[str]:
    """One import cycle of ``graph`` (its modules in order, the first repeated), or []."""
    state: dict[str, int] = {}
    stack: list[str] = []

    def visit(node: str) -> list[str]:
        state[node] = 1
        stack.append(node)
        for nxt in sorted(graph.get(node, ())):
            if state.get(nxt) == 1:
                return [*stack[stack.index(nxt) :], nxt]
            if nxt not in state:
                found = visit(nxt)
                if found:
                    return found
        stack.pop()
        state[node] = 2
        return []

    for node in sorted(graph):
        if node not in state:
            found = visit(node)
            if found:
                return found
    return []


def test_the_modules_of_learners_import_one_another_in_one_direction():
    graph = _module_imports(PACKAGE, "learners")
    assert len(graph) > 5, graph
    cycle = _cycle(graph)
    assert not cycle, "an import cycle in learners/: " + " -> ".join(cycle)


def test_the_cycle_check_sees_a_type_only_import(tmp_path):
    pkg = tmp_path / "mpcmobo" / "learners"
    pkg.mkdir(parents=True)
    (pkg / "a.py").write_text("from mpcmobo.learners.b import B\n")
    (pkg / "b.py").write_text(
        "from typing import TYPE_CHECKING\nif TYPE_CHECKING:\n    from mpcmobo.learners import a\n"
    )
    assert _cycle(_module_imports(tmp_path / "mpcmobo", "learners")) == [
        "mpcmobo.learners.a",
        "mpcmobo.learners.b",
        "mpcmobo.learners.a",
    ]


def test_the_loop_and_the_learners_never_probe_a_learner_with_getattr():
    """The learner contract is declared (docs/architecture.md): the callers call its methods."""
    hits = []
    for sub in ("learners", "experiment"):
        for path in sorted((PACKAGE / sub).glob("*.py")):
            for i, line in enumerate(path.read_text().splitlines(), 1):
                if "getattr(" in line and "learner" in line.lower():
                    hits.append(f"{path.relative_to(PACKAGE.parent)}:{i}: {line.strip()}")
    assert not hits, "\n".join(hits)
