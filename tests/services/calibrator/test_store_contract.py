"""Every store of calibrations keeps the calibrator's store protocol (``magnet.calibrator.store``): the same checks
the store in memory of the core's tests passes (``memory_store.check_store_contract``). A new store: one line in
``STORES``."""

from __future__ import annotations

import contextlib
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest
from memory_store import check_store_contract

from services.calibrator.store import CalibrationStore

#: name -> a store opened in a test's directory (a context manager, closed after the checks)
STORES: dict[str, Callable[[Path], Any]] = {
    "sqlite": lambda directory: CalibrationStore(directory / "c.db"),
}


@pytest.mark.parametrize("name", sorted(STORES))
def test_the_store_keeps_the_store_contract(name, tmp_path):
    with contextlib.closing(STORES[name](tmp_path)) as store:
        check_store_contract(store)
