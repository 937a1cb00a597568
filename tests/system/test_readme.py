"""The README's examples print what they show: every block of ``$ command`` lines followed by their output is run
in a fresh folder (with ``data/`` beside it, as in a clone) by bash with this environment's ``magnet`` first on the
PATH, and each command's output must match the lines shown; numbers match to the digits shown (1e-6 relative, the
last digit of a 7-digit figure), so a change that alters what a user would see fails here until the README says it."""

from __future__ import annotations

import math
import os
import re
import subprocess
import sys
from pathlib import Path

import pytest
from helpers import REPO_ROOT

pytestmark = pytest.mark.integration

NUMBER = re.compile(r"[-+]?\d+\.\d+(?:e[-+]?\d+)?")


def examples(text: str) -> list[list[tuple[str, list[str]]]]:
    """The README's example blocks: each a list of (command, the output lines shown under it)."""
    blocks: list[list[tuple[str, list[str]]]] = []
    current: list[tuple[str, list[str]]] = []
    for line in [*text.splitlines(), ""]:
        if line.startswith("    $ "):
            current.append((line[6:], []))
        elif current and line.startswith("    ") and line.strip():
            current[-1][1].append(line[4:])
        elif current:
            blocks.append(current)
            current = []
    return blocks


def same(shown: str, printed: str) -> bool:
    """Whether a printed line is the line shown, numbers to the digits shown."""
    if NUMBER.sub("#", shown) != NUMBER.sub("#", printed):
        return False
    pairs = zip(NUMBER.findall(shown), NUMBER.findall(printed))
    return all(math.isclose(float(a), float(b), rel_tol=1e-6, abs_tol=1e-12) for a, b in pairs)


def test_the_readme_has_examples_to_run():
    blocks = examples((REPO_ROOT / "README.md").read_text())
    assert sum(len(block) for block in blocks) >= 5 and any(out for block in blocks for _, out in block)


@pytest.mark.parametrize("number", range(len(examples((REPO_ROOT / "README.md").read_text()))))
def test_a_readme_example_prints_what_it_shows(number: int, tmp_path: Path):
    block = examples((REPO_ROOT / "README.md").read_text())[number]
    (tmp_path / "data").symlink_to(REPO_ROOT / "data")
    env = {**os.environ, "PATH": f"{Path(sys.executable).parent}{os.pathsep}{os.environ['PATH']}"}
    for command, shown in block:
        done = subprocess.run(
            ["bash", "-o", "pipefail", "-c", command], cwd=tmp_path, env=env, capture_output=True, text=True,
            timeout=120,
        )  # fmt: skip
        printed = (done.stdout + done.stderr).splitlines()
        assert len(printed) == len(shown) and all(map(same, shown, printed)), (
            f"README example `{command}` printed:\n" + "\n".join(printed) + "\nnot:\n" + "\n".join(shown)
        )
