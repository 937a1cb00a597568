"""Shared test fixtures: where the repository's recordings live (``data/``)."""

from __future__ import annotations

from pathlib import Path

import pytest

REPO_ROOT = Path(__file__).resolve().parents[1]
DATA_DIR = REPO_ROOT / "data"


@pytest.fixture(scope="session")
def datasets_dir() -> Path:
    if not DATA_DIR.is_dir():
        pytest.fail(f"recordings not found at {DATA_DIR}: the repository's data/ folder is missing")
    return DATA_DIR
