"""The functional core stays pure: no module of ``magnet/`` (drivers and emulators included) loads the network, the
bus or the database, and none reads the clock or sleeps by itself (clocks and sleeps are injected)."""

from __future__ import annotations

import ast
import json
import subprocess
import sys
from pathlib import Path

import pytest
from source_trees import nodes, parsed

MAGNET_DIR = Path(__file__).resolve().parents[1] / "magnet"
FORBIDDEN = ("zenoh", "smbus2", "sqlite3", "_sqlite3")
#: modules the shell owns: processes, sockets, threads, signals
FORBIDDEN_SOURCE_IMPORTS = {
    "zenoh",
    "smbus2",
    "sqlite3",
    "socket",
    "subprocess",
    "signal",
    "asyncio",
    "multiprocessing",
    "http",
    "urllib",
}
#: ``time.X(...)`` calls that read a clock or sleep; a module takes them as parameters instead
CLOCK_CALLS = {"sleep", "time", "time_ns", "monotonic", "monotonic_ns", "perf_counter", "perf_counter_ns"}

IMPORT_ALL = """
import importlib, json, pkgutil, sys
import magnet
names = ["magnet"] + [m.name for m in pkgutil.walk_packages(magnet.__path__, "magnet.")]
for name in names:
    importlib.import_module(name)
loaded = sorted(m for m in sys.modules if m.split(".")[0] in %r)
print(json.dumps({"modules": names, "loaded": loaded}))
"""


def _sources() -> list[Path]:
    return sorted(MAGNET_DIR.rglob("*.py"))


@pytest.mark.integration  # a fresh interpreter (a process), so that nothing is imported already
def test_no_module_of_magnet_loads_zenoh_smbus2_or_sqlite3():
    out = subprocess.run(
        [sys.executable, "-c", IMPORT_ALL % (FORBIDDEN,)], capture_output=True, text=True, check=True, timeout=120
    ).stdout
    result = json.loads(out.strip().splitlines()[-1])
    expected = {
        ".".join(p.relative_to(MAGNET_DIR.parent).with_suffix("").parts).removesuffix(".__init__") for p in _sources()
    }
    assert expected <= set(result["modules"]), f"not imported: {sorted(expected - set(result['modules']))}"
    assert result["loaded"] == [], f"importing magnet/ loaded {result['loaded']}"


def _top_level_imports(tree: ast.AST) -> set[str]:
    names = set()
    for node in nodes(tree):
        if isinstance(node, ast.Import):
            names |= {alias.name.split(".")[0] for alias in node.names}
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            names.add(node.module.split(".")[0])
    return names


def _clock_calls(tree: ast.AST) -> list[str]:
    return [
        f"line {node.lineno}: time.{node.func.attr}()"
        for node in nodes(tree)
        if isinstance(node, ast.Call)
        and isinstance(node.func, ast.Attribute)
        and isinstance(node.func.value, ast.Name)
        and node.func.value.id == "time"
        and node.func.attr in CLOCK_CALLS
    ]


def test_magnet_imports_no_shell_module_and_neither_reads_the_clock_nor_sleeps():
    problems = []
    for path in _sources():
        tree = parsed(path)
        name = path.relative_to(MAGNET_DIR.parent)
        problems += [f"{name}: imports {mod}" for mod in sorted(_top_level_imports(tree) & FORBIDDEN_SOURCE_IMPORTS)]
        problems += [f"{name}: {call}" for call in _clock_calls(tree)]
    assert problems == [], "magnet/ must stay pure (inject clocks and sleeps):\n" + "\n".join(problems)


def test_the_guard_covers_every_stage_core():
    """The decisions of the compass and of the calibrator are among the sources the checks above read."""
    packages = {path.parent.relative_to(MAGNET_DIR).as_posix() for path in _sources()}
    assert {"compass", "calibrator"} <= packages
