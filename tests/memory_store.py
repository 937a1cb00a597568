"""A calibration store in memory that keeps the store protocol (``magnet.calibrator.store.CalibrationStore``), for
the calibrator core's tests, and the protocol's contract as checks that any store must pass (this one and the
service's SQLite file alike: ``tests/services/calibrator/test_store_contract.py``)."""

from __future__ import annotations

import dataclasses
import json
from collections.abc import Callable, Mapping
from typing import Any

import numpy as np
import pytest

from magnet import signing, wire
from magnet.calibrator.store import CalibrationStore, MakeRecord
from magnet.model import Calibration


class MemoryStore:
    """Records and their changes in a list, newest last; each kept as the text a database would keep (so a record
    read back went through ``wire.calibration_from_record``, as the SQLite store's do). ``failing``: an OSError every
    call raises (a full disk, a damaged file), nothing changed."""

    def __init__(self) -> None:
        self.rows: list[tuple[str, str, str | None]] = []  # (device, record JSON, change JSON)
        self.failing: OSError | None = None

    def _check(self) -> None:
        if self.failing is not None:
            raise self.failing

    def append(
        self, device: str, make: MakeRecord, change: Mapping[str, Any] | None = None, floor: int = 0
    ) -> tuple[wire.DeviceCalibration, bool]:
        self._check()
        mine = [record for record, _ in self._rows(device)]
        highest = max((record.version for record in mine), default=0)
        record = make(min(max(highest, floor), wire.MAX_VERSION - 1) + 1)
        if record.device != device:
            raise ValueError(f"a record of {record.device} cannot be stored as one of {device}")
        if mine and mine[0].id == record.id:
            return record, False
        text = json.dumps(record.to_record(), sort_keys=True, allow_nan=False)
        self.rows.append((device, text, None if change is None else json.dumps(dict(change), sort_keys=True)))
        return record, True

    def _rows(self, device: str) -> list[tuple[wire.DeviceCalibration, dict[str, Any] | None]]:
        """(record, change) of ``device``, newest first."""
        return [
            (wire.calibration_from_record(json.loads(text)), None if change is None else json.loads(change))
            for stored, text, change in reversed(self.rows)
            if stored == device
        ]

    def latest(self, device: str) -> wire.DeviceCalibration | None:
        self._check()
        return next((record for record, _ in self._rows(device)), None)

    def all_latest(self) -> dict[str, wire.DeviceCalibration]:
        self._check()
        return {device: record for device in {d for d, _, _ in self.rows} if (record := self.latest(device))}

    def history(self, device: str, limit: int | None = None) -> list[wire.DeviceCalibration]:
        return [record for record, _ in self.history_changes(device, limit)]

    def history_changes(
        self, device: str, limit: int | None = None
    ) -> list[tuple[wire.DeviceCalibration, dict[str, Any] | None]]:
        self._check()
        rows = self._rows(device)
        return rows if limit is None else rows[: max(0, limit)]


def calibration(offset_x: float = 1.0) -> Calibration:
    return Calibration("ellipsoid", np.array([offset_x, 2.0, 3.0]), np.eye(3))


def new_signer() -> signing.Signer:
    private_pem, _ = signing.new_key_pair()
    return signing.Signer(signing.load_private_key(private_pem))


def record_of(device: str, version: int, offset_x: float = 1.0, created_ns: int = 7) -> wire.DeviceCalibration:
    return wire.DeviceCalibration(device, created_ns, calibration(offset_x), version=version)


def check_store_contract(store: CalibrationStore) -> None:
    """What every store of calibrations does (``magnet.calibrator.store``): versions per device counted on from
    the store (or ``floor``), a record and its change together, the newest not stored twice, history newest first
    with its changes, a signature served exactly as it was made, a record of another device refused."""
    first, stored = store.append("a", lambda v: record_of("a", v, 1.0), {"action": "auto", "by": ""})
    assert stored and first.version == 1
    _, stored = store.append("a", lambda v: record_of("a", v, 1.0), {"action": "auto", "by": "x"})
    assert not stored, "the record in force is not stored twice"
    second, _ = store.append("a", lambda v: record_of("a", v, 2.0), None)
    other, _ = store.append("b", lambda v: record_of("b", v, 5.0), {"action": "session", "by": "ann"})
    assert (second.version, other.version) == (2, 1), "versions are counted per device"
    high, _ = store.append("a", lambda v: record_of("a", v, 3.0), {"action": "rollback"}, floor=40)
    assert high.version == 41, "floor: the version of the record in force as its JSON says"
    with pytest.raises(ValueError, match="cannot be stored"):
        store.append("a", lambda v: record_of("b", v, 9.0), {"action": "auto"})
    failing: Callable[[int], wire.DeviceCalibration] = lambda v: 1 / 0  # type: ignore[return-value]  # noqa: E731
    with pytest.raises(ZeroDivisionError):
        store.append("a", failing, {"action": "auto"})
    assert [r.version for r in store.history("a")] == [41, 2, 1], "nothing of a failed append is stored"
    assert [r.id for r in store.history("a", limit=2)] == [high.id, second.id]
    changes = [change for _, change in store.history_changes("a")]
    assert changes == [{"action": "rollback"}, None, {"action": "auto", "by": ""}], "each record with its change"
    latest = store.latest("a")
    assert latest is not None and latest.to_record() == high.to_record() and store.latest("nobody") is None
    assert {d: r.id for d, r in store.all_latest().items()} == {"a": high.id, "b": other.id}

    signer = new_signer()
    made = record_of("s", 1, 4.0)
    signed = signer.sign(made.to_record())
    made = dataclasses.replace(made, sig=signed["sig"], key_id=signed["key_id"])
    store.append("s", lambda v: made, {"action": "auto"})
    back = store.latest("s")
    assert back is not None and back.to_record() == made.to_record(), "served exactly as stored"
    signing.TrustedKeys([signer.private_key.public_key()]).verify(back.to_record())
