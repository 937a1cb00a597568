"""The service's SQLite store keeps the calibrator's store protocol (``magnet.calibrator.store``), the same checks
the store in memory of the core's tests passes (``memory_store.check_store_contract``)."""

from __future__ import annotations

from memory_store import check_store_contract

from services.calibrator.store import CalibrationStore


def test_the_sqlite_store_keeps_the_store_contract(tmp_path):
    with CalibrationStore(tmp_path / "c.db") as store:
        check_store_contract(store)
