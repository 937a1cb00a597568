"""A damaged calibration database: one line naming the file and what to do, never a traceback; faults found later
(a damaged page read by a query) become an error reply, and the calibrator keeps serving."""

from __future__ import annotations

import sqlite3

import numpy as np
import pytest
from helpers import NO_SCOUT, free_ports, run_magnet

from magnet import wire
from magnet.model import Calibration
from services.calibrator.queries import answer_history
from services.calibrator.service import Calibrator, CalibratorSettings
from services.calibrator.store import CalibrationStore, StoreError


def _fill(path, devices=60):
    with CalibrationStore(path) as store:
        for i in range(devices):
            store.save(
                wire.DeviceCalibration(
                    f"d-{i}", i, Calibration("ellipsoid", [i, 0.0, 0.0], np.eye(3), reason="x" * 500)
                )
            )
    with sqlite3.connect(path) as db:  # everything in the main file, no WAL left over
        db.execute("PRAGMA wal_checkpoint(TRUNCATE)")


def _damage(path, offset=2 * 4096, length=4096):
    with open(path, "r+b") as handle:
        handle.seek(offset)
        handle.write(b"\xa5" * length)


@pytest.mark.parametrize("damage", ["pages", "not a database"])
def test_damaged_database_is_one_line_naming_the_file_and_what_to_do(tmp_path, damage):
    path = tmp_path / "c.db"
    if damage == "pages":
        _fill(path)
        _damage(path)
    else:
        path.write_bytes(b"this is not a database" * 1000)
    with pytest.raises(StoreError, match=f"{path}.*restore it from a backup, or move it aside"):
        CalibrationStore(path)


@pytest.mark.integration
def test_calibrator_on_a_damaged_database_exits_2_with_one_line(tmp_path):
    path = tmp_path / "c.db"
    _fill(path)
    _damage(path)
    (port,) = free_ports(1)
    out = run_magnet("calibrator", "--db", str(path), *NO_SCOUT, "--listen", f"tcp/127.0.0.1:{port}", timeout=60)
    assert out.returncode == 2
    assert "Traceback" not in out.stderr and str(path) in out.stderr and "move it aside" in out.stderr
    assert len(out.stderr.strip().splitlines()) == 1, out.stderr


class _Query:
    def __init__(self, key, parameters):
        self.key_expr, self.parameters, self.replies, self.errors = key, parameters, [], []

    def reply(self, key, payload):
        self.replies.append(payload)

    def reply_err(self, payload):
        self.errors.append(payload)


def test_a_page_damaged_while_serving_gives_an_error_reply_not_a_crash(tmp_path):
    path = tmp_path / "c.db"
    _fill(path)
    with CalibrationStore(path) as store:
        calibrator = Calibrator(store, CalibratorSettings(), lambda *a: None)
        _damage(path, offset=4096, length=8 * 4096)
        store._db.execute("PRAGMA cache_size=0")  # read the pages again
        query = _Query("magnet/d-5/calibration/history", {"limit": "10"})
        answer_history(query, calibrator, "magnet")
        assert query.errors and b"move it aside" in query.errors[0], (query.replies, query.errors)
        with pytest.raises(StoreError):
            store.save(wire.DeviceCalibration("new", 1, Calibration("ellipsoid", [1.0, 0, 0], np.eye(3))))
