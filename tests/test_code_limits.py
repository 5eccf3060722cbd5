"""Sizes a reader can hold: no function or method of the package over 120 lines, and the
loss's module (objectives/wcsac.py) within 800.

A function's length is from its first decorator (or its ``def``) to its last line, its
docstring and comments included: what a reader scrolls through. Nested functions count
inside their parent and on their own.
"""

from __future__ import annotations

import ast

from _training_helpers import ROOT

PACKAGE = ROOT / "wcsac_rl"
MAX_FUNCTION_LINES = 120
MAX_MODULE_LINES = {"objectives/wcsac.py": 800}


def long_functions(source: str, limit: int = MAX_FUNCTION_LINES) -> list[tuple[str, int]]:
    """``(qualified name, lines)`` of every function of ``source`` longer than ``limit``."""
    found = []

    def visit(node: ast.AST, prefix: str) -> None:
        for child in ast.iter_child_nodes(node):
            if isinstance(child, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)):
                name = f"{prefix}{child.name}"
                if not isinstance(child, ast.ClassDef):
                    first = min([child.lineno, *(d.lineno for d in child.decorator_list)])
                    lines = child.end_lineno - first + 1
                    if lines > limit:
                        found.append((name, lines))
                visit(child, f"{name}.")
            else:
                visit(child, prefix)

    visit(ast.parse(source), "")
    return found


def test_the_walker_measures_functions_and_methods():
    """A 3-line method inside a class, with its decorator, is found at limit 2 and not at 3."""
    source = "class A:\n    @staticmethod\n    def f():\n        return 1\n\ndef g():\n    pass\n"
    assert long_functions(source, limit=2) == [("A.f", 3)]
    assert long_functions(source, limit=3) == []
    nested = "def outer():\n    def inner():\n        x = 1\n        return x\n    return inner\n"
    assert long_functions(nested, limit=3) == [("outer", 5)]
    assert long_functions(nested, limit=2) == [("outer", 5), ("outer.inner", 3)]


def test_no_function_of_the_package_is_over_120_lines():
    found = [
        f"{path.relative_to(ROOT)}: {name} ({lines} lines)"
        for path in sorted(PACKAGE.rglob("*.py"))
        for name, lines in long_functions(path.read_text(encoding="utf-8"))
    ]
    assert found == []


def test_the_limited_modules_are_within_their_limits():
    found = {
        module: len((PACKAGE / module).read_text(encoding="utf-8").splitlines())
        for module in MAX_MODULE_LINES
    }
    assert {m: n for m, n in found.items() if n > MAX_MODULE_LINES[m]} == {}
