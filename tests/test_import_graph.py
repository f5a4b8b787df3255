"""The import graph of pcrcg has no cycles (issue 17): the sources are read with ``ast``, no pcrcg
module is imported (no torch either).

Every ``import`` / ``from ... import`` of a pcrcg module counts, at module level and inside functions
(an import hidden in a function to dodge a cycle is still a cycle), relative imports resolved. A name
imported from a package counts as its submodule when there is one (``from pcrcg.vision import
matching``), else as the package; the parent packages Python initialises on the way are not edges.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

PKG = Path(__file__).resolve().parents[1] / "pcrcg"


def _modules(pkg: Path) -> dict[str, tuple[Path, bool]]:
    """Dotted name -> (file, is a package's ``__init__``)."""
    out = {}
    for p in sorted(pkg.rglob("*.py")):
        parts = list(p.relative_to(pkg.parent).with_suffix("").parts)
        is_pkg = parts[-1] == "__init__"
        out[".".join(parts[:-1] if is_pkg else parts)] = (p, is_pkg)
    return out


def import_graph(pkg: Path = PKG) -> dict[str, dict[str, int]]:
    """Module -> {imported module of the package ``pkg``: line of its first import}."""
    mods = _modules(pkg)
    top = pkg.name

    def resolve(name: str) -> str | None:
        while name and name not in mods:
            name = name.rpartition(".")[0]
        return name or None

    graph: dict[str, dict[str, int]] = {}
    for mod, (path, is_pkg) in mods.items():
        here = mod if is_pkg else mod.rpartition(".")[0]
        edges: dict[str, int] = {}
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"), str(path))):
            if isinstance(node, ast.Import):
                targets = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom):
                base = node.module or ""
                if node.level:
                    pkg = here
                    for _ in range(node.level - 1):
                        pkg = pkg.rpartition(".")[0]
                    base = f"{pkg}.{base}" if base else pkg
                targets = [f"{base}.{a.name}" for a in node.names]
            else:
                continue
            for t in targets:
                if t == top or t.startswith(top + "."):
                    target = resolve(t)
                    if target and target != mod:
                        edges.setdefault(target, node.lineno)
        graph[mod] = edges
    return graph


def import_cycles(graph: dict[str, dict[str, int]]) -> list[list[str]]:
    """The strongly connected components with more than one module (Tarjan, iterative)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    cycles: list[list[str]] = []
    for root in sorted(graph):
        if root in index:
            continue
        work = [(root, iter(sorted(graph[root])))]
        index[root] = low[root] = len(index)
        stack.append(root)
        on_stack.add(root)
        while work:
            v, children = work[-1]
            w = next(children, None)
            if w is not None:
                if w not in index:
                    index[w] = low[w] = len(index)
                    stack.append(w)
                    on_stack.add(w)
                    work.append((w, iter(sorted(graph[w]))))
                elif w in on_stack:
                    low[v] = min(low[v], index[w])
                continue
            work.pop()
            if work:
                low[work[-1][0]] = min(low[work[-1][0]], low[v])
            if low[v] == index[v]:
                comp = []
                while True:
                    w = stack.pop()
                    on_stack.discard(w)
                    comp.append(w)
                    if w == v:
                        break
                if len(comp) > 1:
                    cycles.append(sorted(comp))
    return cycles


@pytest.fixture(scope="module")
def pcrcg_graph() -> dict[str, dict[str, int]]:
    return import_graph()


def test_the_checker_finds_a_cycle():
    graph = {"a": {"b": 1}, "b": {"c": 2}, "c": {"a": 3}, "d": {"a": 4}, "e": {}}
    assert import_cycles(graph) == [["a", "b", "c"]]
    assert import_cycles({"a": {"b": 1}, "b": {}}) == []


def test_the_graph_sees_function_level_and_relative_imports(tmp_path, pcrcg_graph):
    pkg = tmp_path / "toy"
    (pkg / "sub").mkdir(parents=True)
    (pkg / "__init__.py").write_text("")
    (pkg / "sub" / "__init__.py").write_text("from . import b\n")
    (pkg / "sub" / "a.py").write_text("import os\n\ndef f():\n    from toy.sub.b import g\n    return g\n")
    (pkg / "sub" / "b.py").write_text("from .a import f\nfrom .. import c\n")
    (pkg / "c.py").write_text("")
    graph = import_graph(pkg)
    assert graph["toy.sub"] == {"toy.sub.b": 1}
    assert graph["toy.sub.a"] == {"toy.sub.b": 4}  # inside a function
    assert graph["toy.sub.b"] == {"toy.sub.a": 1, "toy.c": 2}  # relative
    assert import_cycles(graph) == [["toy.sub.a", "toy.sub.b"]]

    assert len(pcrcg_graph) > 50
    assert "pcrcg.vision.keypoints" in pcrcg_graph["pcrcg.vision.matching"]  # module level
    assert "pcrcg.vision.pretrain" in pcrcg_graph["pcrcg.vision.matching"]  # inside covisibility()


def test_no_import_cycles_among_pcrcg_modules(pcrcg_graph):
    graph = pcrcg_graph
    cycles = import_cycles(graph)
    lines = []
    for comp in cycles:
        members = set(comp)
        lines.append(" <-> ".join(comp) + ": " + "; ".join(
            f"{a} imports {b} (line {ln})" for a in comp for b, ln in sorted(graph[a].items()) if b in members))
    assert not cycles, "import cycles among pcrcg modules (give each concept one home, imports one way):\n" + \
        "\n".join(lines)
