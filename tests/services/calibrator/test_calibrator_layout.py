"""The calibrator's modules stay small enough to read in one sitting, its public names stay where they were, its
decisions (``magnet/calibrator/``) import nothing of the process (``services/calibrator/``: at most 8 modules)."""

from __future__ import annotations

import ast
import re
from pathlib import Path

from source_trees import nodes, parsed

ROOT = Path(__file__).resolve().parents[3]
CORE = ROOT / "magnet" / "calibrator"
SHELL = ROOT / "services" / "calibrator"
MAX_MODULE_LINES = 350
MAX_SHELL_MODULES = 8
#: what the calibrator's decisions never import: the process's modules, the network, the database, threads
SHELL_ONLY = ("services", "zenoh", "sqlite3", "_sqlite3", "threading", "socket", "subprocess", "asyncio")


def _modules(directory: Path) -> list[Path]:
    return sorted(directory.glob("*.py"))


def test_every_calibrator_module_is_short():
    long = {
        str(path.relative_to(ROOT)): n
        for path in _modules(CORE) + _modules(SHELL)
        if (n := len(path.read_text().splitlines())) > MAX_MODULE_LINES
    }
    assert long == {}, f"calibrator modules over {MAX_MODULE_LINES} lines: {long}"


def test_the_service_keeps_the_process_only_in_at_most_eight_modules():
    names = [path.stem for path in _modules(SHELL)]
    assert len(names) <= MAX_SHELL_MODULES, names
    assert {"service", "intake", "lease", "store", "queries", "settings"} <= set(names)


def test_the_service_module_still_offers_its_names():
    from services.calibrator import service

    for name in ("Calibrator", "CalibratorSettings", "ServiceSettings", "add_arguments", "run", "run_calibrator"):
        assert hasattr(service, name), name


def _imported(path: Path) -> set[str]:
    found: set[str] = set()
    for node in nodes(parsed(path)):
        if isinstance(node, ast.Import):
            found |= {alias.name for alias in node.names}
        elif isinstance(node, ast.ImportFrom) and node.module:
            found.add(node.module)
            found |= {f"{node.module}.{alias.name}" for alias in node.names}
    return found


def test_the_decisions_import_nothing_of_the_process():
    found = {
        f"{path.name}: {name}"
        for path in _modules(CORE)
        for name in _imported(path)
        if name.split(".")[0] in SHELL_ONLY
    }
    assert found == set()


def _parts_graph() -> dict[str, set[str]]:
    """module of magnet/calibrator -> the parts it imports (``magnet.calibrator.X`` named ``X``)."""
    prefix = "magnet.calibrator."
    return {
        path.stem: {name[len(prefix) :].split(".")[0] for name in _imported(path) if name.startswith(prefix)}
        for path in _modules(CORE)
    }


def test_the_calibrators_parts_import_each_other_one_way():
    graph = _parts_graph()
    done: set[str] = set()

    def visit(module: str, path: tuple[str, ...]) -> None:
        assert module not in path, f"import circle: {' -> '.join((*path, module))}"
        if module in done:
            return
        for imported in graph.get(module, ()):
            visit(imported, (*path, module))
        done.add(module)

    for module in graph:
        if module != "__init__":
            visit(module, ())
    for bottom in ("status", "keys", "store", "settings", "signatures"):
        assert graph[bottom] == set(), f"{bottom} imports {graph[bottom]}"
    assert {m for m, imported in graph.items() if "core" in imported} == {"__init__"}
    users = {path.stem for path in _modules(SHELL) if "magnet.calibrator.core" in _imported(path)}
    assert users == {"queries", "service"}


def test_no_part_calls_a_private_name_of_another():
    private = re.compile(r"\b(?!self\b|cls\b)[a-z_]\w*\._[a-z]\w*")
    found = [
        f"{path.name}: {match.group()}"
        for path in _modules(CORE) + _modules(SHELL)
        for match in private.finditer(path.read_text())
    ]
    assert found == []
