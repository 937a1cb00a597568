"""Every store of calibrations keeps the calibrator's store protocol (``magnet.calibrator.store``): the same checks
the store in memory of the core's tests passes (``memory_store.check_store_contract``). A new store: one line in
``STORES``."""

from __future__ import annotations

import contextlib
from collections.abc import Callable
from typing import Any

import pytest
from memory_store import check_store_contract

from services.calibrator.store import CalibrationStore, open_store
from services.common.stores import parse_db

#: name -> a store opened in a test's directory or a new database of the session's PostgreSQL server (the request
#: gives either), closed after the checks
STORES: dict[str, Callable[[pytest.FixtureRequest], Any]] = {
    "sqlite": lambda request: CalibrationStore(request.getfixturevalue("tmp_path") / "c.db"),
    "postgresql": lambda request: open_store(parse_db(request.getfixturevalue("postgres_url"))),
}
#: stores that need a server the tests start (integration)
SERVED = {"postgresql"}


@pytest.mark.parametrize(
    "name", [pytest.param(name, marks=[pytest.mark.integration] if name in SERVED else []) for name in sorted(STORES)]
)
def test_the_store_keeps_the_store_contract(name, request):
    with contextlib.closing(STORES[name](request)) as store:
        check_store_contract(store)
