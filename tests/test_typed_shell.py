"""The shell typed: no zenoh object annotated ``Any`` in ``services/``, and no declaration undeclared by hand.

zenoh 1.x ships its types (``zenoh.Session``, ``zenoh.Subscriber[zenoh.Handler[zenoh.Sample]]``, ``zenoh.Query``,
``zenoh.Reply`` ...), so a parameter, attribute, variable or return whose name says it holds a zenoh object
(session, subscriber, queryable, query, sample, reply, publisher, token, handler; plurals and ``sub`` too) and whose
annotation mentions ``Any`` is a loss of checking this test refuses. Declarations (subscribers, queryables,
publishers, liveliness tokens) live in ``with`` blocks or a ``contextlib.ExitStack``: a call to ``.undeclare()`` is
refused too, unless its line says ``# lifetime: ...`` why the declaration follows a state rather than a block (a
liveliness token that comes and goes with a device's health).

``NOT_YET``: files other branches of this round are converting; the lead empties it when they merge.
"""

from __future__ import annotations

import ast
import functools
from pathlib import Path

import pytest
from source_trees import nodes, parsed

ROOT = Path(__file__).resolve().parents[1]
SERVICES = ROOT / "services"

ZENOH_WORDS = {"session", "sub", "subscriber", "queryable", "query", "sample", "reply", "publisher", "token", "handler"}

#: converted on other branches of this round (compass, calibrator, edge): emptied by the lead at merge
NOT_YET: set[str] = set()


def _zenohish(name: str) -> bool:
    for part in name.lower().strip("_").split("_"):
        if part.endswith("ies"):
            part = part[:-3] + "y"
        elif part.endswith("s") and not part.endswith("ss"):
            part = part[:-1]
        if part in ZENOH_WORDS:
            return True
    return False


def _mentions_any(annotation: ast.expr | None) -> bool:
    if annotation is None:
        return False
    for node in ast.walk(annotation):
        if isinstance(node, ast.Name) and node.id == "Any":
            return True
        if isinstance(node, ast.Attribute) and node.attr == "Any":
            return True
        if isinstance(node, ast.Constant) and isinstance(node.value, str) and "Any" in node.value:
            return True
    return False


def _is_any(annotation: ast.expr | None) -> bool:
    """Whether a return annotation is ``Any`` itself (or ``Any | None``): what a function named for a zenoh object
    returns; a ``dict[str, Any]`` is JSON (an operator session's answer, a reply's body), not a zenoh object."""
    if isinstance(annotation, ast.BinOp):
        return _is_any(annotation.left) or _is_any(annotation.right)
    if isinstance(annotation, ast.Constant) and isinstance(annotation.value, str):
        return annotation.value.replace(" ", "") in ("Any", "Any|None", "None|Any")
    return (isinstance(annotation, ast.Name) and annotation.id == "Any") or (
        isinstance(annotation, ast.Attribute) and annotation.attr == "Any"
    )


def _target_name(target: ast.expr) -> str | None:
    if isinstance(target, ast.Name):
        return target.id
    if isinstance(target, ast.Attribute):
        return target.attr
    return None


def untyped_zenoh(tree: ast.AST) -> list[tuple[int, str]]:
    """(line, what) of every zenoh-named parameter, attribute, variable or return annotated with ``Any``."""
    found = []
    for node in nodes(tree):
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
            args = node.args
            every = [*args.posonlyargs, *args.args, *args.kwonlyargs, args.vararg, args.kwarg]
            found += [
                (arg.lineno, f"parameter {arg.arg} of {node.name}")
                for arg in every
                if arg is not None and _zenohish(arg.arg) and _mentions_any(arg.annotation)
            ]
            if _zenohish(node.name) and _is_any(node.returns):
                found.append((node.lineno, f"return of {node.name}"))
        elif isinstance(node, ast.AnnAssign):
            name = _target_name(node.target)
            if name is not None and _zenohish(name) and _mentions_any(node.annotation):
                found.append((node.lineno, f"{name}"))
    return sorted(found, key=lambda item: item[0])


def undeclared_by_hand(tree: ast.AST) -> list[tuple[int, str]]:
    """(line, what) of every ``.undeclare()`` call."""
    return [
        (node.lineno, "undeclare()")
        for node in nodes(tree)
        if isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute) and node.func.attr == "undeclare"
    ]


def _files() -> list[Path]:
    return sorted(SERVICES.rglob("*.py"))


@functools.cache
def _trees() -> tuple[tuple[Path, ast.Module], ...]:
    """Every file of services/ not in NOT_YET, parsed once for both checks."""
    return tuple((path, parsed(path)) for path in _files() if not _not_yet(path))


def _not_yet(path: Path) -> bool:
    name = path.relative_to(ROOT).as_posix()
    return any(name.startswith(prefix) for prefix in NOT_YET)


@pytest.mark.parametrize("check", [untyped_zenoh, undeclared_by_hand], ids=["Any", "undeclare"])
def test_no_zenoh_object_untyped_or_undeclared_by_hand(check):
    problems = []
    for path, tree in _trees():
        lines = path.read_text().splitlines()
        problems += [
            f"{path.relative_to(ROOT)}:{line}: {what}"
            for line, what in check(tree)
            if "# lifetime:" not in lines[line - 1]
        ]
    assert not problems, "use zenoh's own types and a with block or an ExitStack:\n" + "\n".join(problems)


def test_the_checks_catch_what_they_are_for():
    bad = ast.parse(
        "from typing import Any\n"
        "def f(session: Any, samples: list[Any], name: Any) -> None:\n"
        "    sub.undeclare()\n"
        "class C:\n"
        "    def __init__(self) -> None:\n"
        "        self.replies: dict[str, Any] = {}\n"
        "def open_session() -> Any: ...\n"
        "def json(message: dict[str, Any]) -> Any: ...\n"
    )
    assert [what for _, what in untyped_zenoh(bad)] == [
        "parameter session of f",
        "parameter samples of f",
        "replies",
        "return of open_session",
    ]
    assert undeclared_by_hand(bad) == [(3, "undeclare()")]


def test_the_files_not_yet_converted_are_still_there():
    """An entry of NOT_YET that names nothing is stale: remove it."""
    for prefix in NOT_YET:
        assert any(p.relative_to(ROOT).as_posix().startswith(prefix) for p in _files()), prefix
