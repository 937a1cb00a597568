"""Each function does one step and each module holds one idea: no function of ``magnet/`` or ``services/`` over
about 40 lines of code, no module over 400 lines.

A function's length is the number of lines on which one of its statements starts, its docstring left out: ``ruff
format`` lays a long call out one argument per line, and that layout should not count as more steps.
"""

from __future__ import annotations

import ast
from pathlib import Path

from source_trees import lines_between, nodes, parsed, statement_lines

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("magnet", "services")
MAX_FUNCTION_LINES = 40


def _sources() -> list[Path]:
    return sorted(path for package in PACKAGES for path in (ROOT / package).rglob("*.py"))


def _functions(tree: ast.AST) -> list[ast.FunctionDef | ast.AsyncFunctionDef]:
    return [node for node in nodes(tree) if isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef)]


def _code_lines(function: ast.FunctionDef | ast.AsyncFunctionDef, tree: ast.AST) -> int:
    """The lines of ``tree`` (the function's module) on which a statement of the function's body starts, nested
    ones included: a body is one run of lines, from its first statement to the function's end."""
    body = function.body
    if body and isinstance(body[0], ast.Expr) and isinstance(body[0].value, ast.Constant):
        body = body[1:]  # the docstring
    if not body:
        return 0
    return lines_between(statement_lines(tree), body[0].lineno, function.end_lineno or body[-1].lineno)


def test_the_sources_are_found():
    names = {path.relative_to(ROOT).as_posix() for path in _sources()}
    assert {"magnet/model/__init__.py", "services/cli.py"} <= names


def test_a_long_function_is_found():
    source = "def f():\n    '''doc'''\n" + "".join(f"    x{i} = (\n        {i}\n    )\n" for i in range(41))
    tree = ast.parse(source)
    (function,) = _functions(tree)
    assert _code_lines(function, tree) == 41


def test_no_function_is_over_40_lines():
    long = [
        f"{path.relative_to(ROOT).as_posix()}:{node.lineno} {node.name} ({length} lines)"
        for path in _sources()
        for node in _functions(parsed(path))
        if (length := _code_lines(node, parsed(path))) > MAX_FUNCTION_LINES
    ]
    assert long == [], f"functions over {MAX_FUNCTION_LINES} lines (split them by step):\n" + "\n".join(long)


MAX_MODULE_LINES = 400


def test_no_module_is_over_400_lines():
    """Each module holds one idea: none of ``magnet/`` or ``services/`` over 400 lines (split it by idea)."""
    long = [
        f"{path.relative_to(ROOT).as_posix()} ({length} lines)"
        for path in _sources()
        if (length := len(path.read_text().splitlines())) > MAX_MODULE_LINES
    ]
    assert long == [], f"modules over {MAX_MODULE_LINES} lines (split them by idea):\n" + "\n".join(long)
