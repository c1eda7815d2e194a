"""No function or method in the package is longer than 80 lines (``def`` to its last line, by the AST):
a longer one is split into named parts, so that each reads in one screen."""

from __future__ import annotations

import ast
from pathlib import Path

PACKAGE_DIR = Path(__file__).resolve().parents[1] / "idas_sumo"
MAX_LINES = 80


def long_functions(source: str, limit: int = MAX_LINES) -> list[tuple[str, int, int]]:
    """(qualified name, first line, length in lines) of every function in ``source`` over ``limit`` lines;
    nested functions and methods are named by their enclosing classes and functions."""
    found: list[tuple[str, int, int]] = []

    def visit(node: ast.AST, prefix: str) -> None:
        for child in ast.iter_child_nodes(node):
            if isinstance(child, ast.FunctionDef | ast.AsyncFunctionDef | ast.ClassDef):
                name = f"{prefix}{child.name}"
                if not isinstance(child, ast.ClassDef):
                    length = (child.end_lineno or child.lineno) - child.lineno + 1
                    if length > limit:
                        found.append((name, child.lineno, length))
                visit(child, f"{name}.")
            else:
                visit(child, prefix)

    visit(ast.parse(source), "")
    return found


def test_no_function_in_the_package_is_over_80_lines() -> None:
    offenders = [
        f"{path.relative_to(PACKAGE_DIR.parent)}:{line} {name}: {length} lines"
        for path in sorted(PACKAGE_DIR.rglob("*.py"))
        for name, line, length in long_functions(path.read_text(encoding="utf-8"))
    ]
    assert offenders == [], f"functions over {MAX_LINES} lines (split them):\n" + "\n".join(offenders)


def test_the_length_counts_from_def_to_the_last_line() -> None:
    """80 lines pass and 81 fail; methods and nested functions are found and named; a decorator is not
    counted."""

    def body(indent: int) -> str:  # 79 statements: with its def line, a function of 80 lines
        return "".join(f"{' ' * indent}x{i} = {i}\n" for i in range(79))

    source = (
        f"def fits():\n{body(4)}"  # lines 1-80
        f"@staticmethod\ndef too_long():\n{body(4)}    return x0\n"  # def on 82, to 162
        f"class C:\n    def method(self):\n        def inner():\n{body(12)}"  # class 163, method 164, inner 165
        "            return 1\n        return inner\n"  # inner ends on 245, method on 246
    )
    assert long_functions(source) == [
        ("too_long", 82, 81),
        ("C.method", 164, 83),
        ("C.method.inner", 165, 81),
    ]
    assert long_functions(source, limit=83) == []
