"""The project's own source files parsed once per test run, for the tests that read the code itself (sizes, imports,
the typed shell, the calibrator's layout)."""

from __future__ import annotations

import ast
import functools
from pathlib import Path


@functools.cache
def parsed(path: Path) -> ast.Module:
    """The syntax tree of ``path`` (a file of magnet/ or services/), parsed on first use."""
    return ast.parse(path.read_text(), filename=str(path))
