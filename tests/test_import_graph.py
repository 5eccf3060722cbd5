"""The package's layers point one way: no import cycles, nothing in training/ imports evaluation/.

Every ``import`` of a ``wcsac_rl`` module counts, at module level or inside a function
(a lazy import still couples the two modules), as an edge from the importing module
to the imported one (``from wcsac_rl.a import b`` to ``wcsac_rl.a.b`` when that is a
module, else to ``wcsac_rl.a``). Parent packages are not implied, as in Python's own
bookkeeping of who imports whom.
"""

from __future__ import annotations

import ast
from pathlib import Path

from _training_helpers import ROOT

PACKAGE = ROOT / "wcsac_rl"


def _modules() -> dict[str, Path]:
    modules = {}
    for path in PACKAGE.rglob("*.py"):
        parts = path.relative_to(ROOT).with_suffix("").parts
        if parts[-1] == "__init__":
            parts = parts[:-1]
        modules[".".join(parts)] = path
    return modules


def _target(name: str, modules: dict[str, Path]) -> str | None:
    while name not in modules and "." in name:
        name = name.rsplit(".", 1)[0]
    return name if name in modules else None


def import_graph() -> dict[str, set[str]]:
    """``module → the wcsac_rl modules it imports`` for every module of the package."""
    modules = _modules()
    graph: dict[str, set[str]] = {name: set() for name in modules}
    for name, path in modules.items():
        package = name if path.name == "__init__.py" else name.rsplit(".", 1)[0]
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            targets: list[str] = []
            if isinstance(node, ast.Import):
                targets = [alias.name for alias in node.names]
            elif isinstance(node, ast.ImportFrom):
                base = node.module or ""
                if node.level:  # relative: up from this module's package
                    anchor = package.split(".")[: len(package.split(".")) - (node.level - 1)]
                    base = ".".join([*anchor, base] if base else anchor)
                targets = [f"{base}.{alias.name}" for alias in node.names]
            for target in targets:
                resolved = _target(target, modules) if target.startswith("wcsac_rl") else None
                if resolved is not None and resolved != name:
                    graph[name].add(resolved)
    return graph


def _cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected components with more than one module (Tarjan)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    found: list[list[str]] = []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in sorted(graph[v]):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            component = []
            while True:
                w = stack.pop()
                on_stack.discard(w)
                component.append(w)
                if w == v:
                    break
            if len(component) > 1:
                found.append(sorted(component))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return found


def test_the_graph_sees_known_edges():
    """The walker finds real imports (else the tests below could never fail)."""
    graph = import_graph()
    assert "wcsac_rl.objectives" in graph["wcsac_rl.training.builders"]  # the package
    assert "wcsac_rl.envs.info" in graph["wcsac_rl.envs.batched_gym"]
    assert "wcsac_rl.training.registry" in graph["wcsac_rl.training.config"]
    assert _cycles({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == [["a", "b", "c"]]


def test_no_import_cycles():
    assert _cycles(import_graph()) == []


def test_training_never_imports_evaluation():
    graph = import_graph()
    upward = sorted(
        (module, target)
        for module, targets in graph.items()
        if module.startswith("wcsac_rl.training")
        for target in targets
        if target.startswith("wcsac_rl.evaluation")
    )
    assert upward == []
