"""tests/ mirrors the code: each test file lies in the folder of what it tests (``tests/magnet/<package>/``,
``tests/services/<stage>/``, or ``tests/system/`` for runs across several services), only the layout guards stay at
the top, and no two test files share a name (the folders have no ``__init__.py``, so pytest imports each test file
by its name alone)."""

from __future__ import annotations

from collections import Counter
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
TESTS = ROOT / "tests"
GUARDS = {"test_imports.py", "test_layout.py", "test_size.py", "test_typed_shell.py"}


def _test_files() -> list[Path]:
    return sorted(TESTS.rglob("test_*.py"))


def _home(path: Path) -> str | None:
    """Why ``path`` is out of place, or None when it lies where the tree says."""
    parts = path.relative_to(TESTS).parts
    if len(parts) == 1:
        return None if parts[0] in GUARDS else "at the top, where only the layout guards are"
    if parts[0] == "system":
        return None if len(parts) == 2 else "below tests/system/"
    if parts[0] not in ("magnet", "services"):
        return f"in tests/{parts[0]}/, which mirrors nothing"
    folder = ROOT.joinpath(*parts[:-1])
    return None if folder.is_dir() else f"in a folder that mirrors no package ({folder.relative_to(ROOT)}/ is absent)"


def test_every_test_file_lies_in_the_mirrored_tree():
    misplaced = {str(p.relative_to(ROOT)): why for p in _test_files() if (why := _home(p)) is not None}
    assert not misplaced, (
        f"move these into tests/magnet/<package>/, tests/services/<stage>/ or tests/system/: {misplaced}"
    )


def test_no_two_test_files_share_a_name():
    names = Counter(p.name for p in _test_files())
    assert not [n for n, count in names.items() if count > 1], sorted(n for n, c in names.items() if c > 1)
