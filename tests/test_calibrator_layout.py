"""The calibrator's modules stay small enough to read in one sitting, and its public names stay where they were."""

from __future__ import annotations

import ast
import re
from pathlib import Path

from source_trees import nodes, parsed

ROOT = Path(__file__).resolve().parents[1]
MAX_MODULE_LINES = 350


def test_every_calibrator_module_is_short():
    long = {
        path.name: n
        for path in sorted((ROOT / "services" / "calibrator").glob("*.py"))
        if (n := len(path.read_text().splitlines())) > MAX_MODULE_LINES
    }
    assert long == {}, f"calibrator modules over {MAX_MODULE_LINES} lines: {long}"


def test_the_service_module_still_offers_its_names():
    from services.calibrator import service

    for name in ("Calibrator", "CalibratorSettings", "ServiceSettings", "add_arguments", "run", "run_calibrator"):
        assert hasattr(service, name), name


def _imports() -> dict[str, set[str]]:
    """module -> the calibrator modules it imports (``services.calibrator.X`` named ``X``)."""
    graph: dict[str, set[str]] = {}
    for path in sorted((ROOT / "services" / "calibrator").glob("*.py")):
        found: set[str] = set()
        for node in nodes(parsed(path)):
            if isinstance(node, ast.ImportFrom) and node.module == "services.calibrator":
                found |= {alias.name for alias in node.names}
            elif isinstance(node, ast.ImportFrom) and (node.module or "").startswith("services.calibrator."):
                found.add(node.module.rsplit(".", 1)[1])
        graph[path.stem] = found
    return graph


def test_the_calibrators_parts_import_each_other_one_way():
    graph = _imports()
    done: set[str] = set()

    def visit(module: str, path: tuple[str, ...]) -> None:
        assert module not in path, f"import circle: {' -> '.join((*path, module))}"
        if module in done:
            return
        for imported in graph.get(module, ()):
            visit(imported, (*path, module))
        done.add(module)

    for module in graph:
        visit(module, ())
    for bottom in ("status", "lease", "intake", "store", "signatures"):
        assert graph[bottom] == set(), f"{bottom} imports {graph[bottom]}"
    assert {m for m, imported in graph.items() if "core" in imported} == {"queries", "service"}


def test_no_part_calls_a_private_name_of_another():
    private = re.compile(r"\b(?!self\b|cls\b)[a-z_]\w*\._[a-z]\w*")
    found = [
        f"{path.name}: {match.group()}"
        for path in sorted((ROOT / "services" / "calibrator").glob("*.py"))
        for match in private.finditer(path.read_text())
    ]
    assert found == []
