"""Shared test fixtures: where the shared datasets live."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

REPO_ROOT = Path(__file__).resolve().parents[1]
SHARED = Path(os.environ.get("MAGNET_SHARED", REPO_ROOT.parent / "shared"))


@pytest.fixture(scope="session")
def datasets_dir() -> Path:
    path = SHARED / "datasets"
    if not path.is_dir():
        pytest.fail(f"shared datasets not found at {path}: set MAGNET_SHARED to the folder that holds datasets/")
    return path
