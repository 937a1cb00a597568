"""Shared test fixtures: where the repository's recordings live (``data/``), and processes stopped after a test."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import pytest
from helpers import Processes

REPO_ROOT = Path(__file__).resolve().parents[1]
DATA_DIR = REPO_ROOT / "data"


@pytest.fixture(scope="session")
def datasets_dir() -> Path:
    if not DATA_DIR.is_dir():
        pytest.fail(f"recordings not found at {DATA_DIR}: the repository's data/ folder is missing")
    return DATA_DIR


@pytest.fixture
def procs(tmp_path: Path) -> Iterator[Processes]:
    """``magnet`` processes for one test (logs in tmp_path), all stopped when the test ends."""
    processes = Processes(tmp_path)
    yield processes
    processes.stop_all()
