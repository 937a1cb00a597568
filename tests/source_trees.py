"""The project's own source files parsed once per test run, for the tests that read the code itself (sizes, imports,
the typed shell, the calibrator's layout), and the nodes of each tree listed once for the checks that go over them."""

from __future__ import annotations

import ast
import bisect
import functools
from pathlib import Path


@functools.cache
def parsed(path: Path) -> ast.Module:
    """The syntax tree of ``path`` (a file of magnet/ or services/), parsed on first use."""
    return ast.parse(path.read_text(), filename=str(path))


@functools.cache
def nodes(tree: ast.AST) -> tuple[ast.AST, ...]:
    """Every node of ``tree``, as ``ast.walk`` gives them, walked once per tree (a tree is kept by identity)."""
    return tuple(ast.walk(tree))


@functools.cache
def statement_lines(tree: ast.AST) -> tuple[int, ...]:
    """The lines (1-based, ascending, each once) on which a statement of ``tree`` starts."""
    return tuple(sorted({node.lineno for node in nodes(tree) if isinstance(node, ast.stmt)}))


def lines_between(lines: tuple[int, ...], first: int, last: int) -> int:
    """How many of ``lines`` (ascending) are in ``first..last``."""
    return bisect.bisect_right(lines, last) - bisect.bisect_left(lines, first)
