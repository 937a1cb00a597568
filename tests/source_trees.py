"""The project's own source files parsed once per test run, for the tests that read the code itself (sizes, imports,
the typed shell, the calibrator's layout), and the nodes of each tree listed once for the checks that go over them."""

from __future__ import annotations

import ast
import bisect
import functools
import gc
from pathlib import Path


@functools.cache
def parsed(path: Path) -> ast.Module:
    """The syntax tree of ``path`` (a file of magnet/ or services/), parsed on first use.

    The trees of all the sources are about 300,000 objects kept to the end of the run: they are moved out of the
    garbage collector's sight (``gc.freeze``, as conftest.py does after collecting), else each of its later full
    collections would walk them all again."""
    tree = ast.parse(path.read_text(), filename=str(path))
    gc.freeze()
    return tree


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
