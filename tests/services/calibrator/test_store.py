"""SQLite calibration store: history newest first, idempotent saves, survives reopening and a killed writer."""

import json
import sqlite3
import subprocess
import sys

import numpy as np
import pytest

from magnet import wire
from magnet.model import Calibration
from services.calibrator.store import CalibrationStore


def _record(device, offset, t):
    return wire.DeviceCalibration(device, t, Calibration("ellipsoid", offset, np.eye(3)))


def test_history_newest_first_and_latest_per_device(tmp_path):
    with CalibrationStore(tmp_path / "c.db") as store:
        assert store.latest("a") is None
        assert store.save(_record("a", [1, 0, 0], 1))
        assert store.save(_record("a", [2, 0, 0], 2))
        assert store.save(_record("b", [3, 0, 0], 3))
        assert not store.save(_record("a", [2, 0, 0], 4)), "identical to the one in force: not stored again"
        assert [r.calibration.offset[0] for r in store.history("a")] == [2, 1]
        assert [r.calibration.offset[0] for r in store.history("a", limit=1)] == [2]
        assert {d: r.calibration.offset[0] for d, r in store.all_latest().items()} == {"a": 2, "b": 3}
    with CalibrationStore(tmp_path / "c.db") as again:
        assert again.latest("a").id == _record("a", [2, 0, 0], 0).id
        mode = again._db.execute("PRAGMA journal_mode").fetchone()[0]
        assert mode == "wal"


@pytest.mark.integration
def test_kill_9_during_writes_leaves_complete_records(tmp_path):
    path = tmp_path / "c.db"
    code = (
        "import sys, numpy as np\n"
        "from magnet import wire\nfrom magnet.model import Calibration\n"
        "from services.calibrator.store import CalibrationStore\n"
        f"s = CalibrationStore({str(path)!r})\n"
        "i = 0\n"
        "while True:\n"
        "    i += 1\n"
        "    s.save(wire.DeviceCalibration('a', i, Calibration('ellipsoid', [i, 0, 0], np.eye(3))))\n"
        "    if i == 20: print('go', flush=True)\n"
    )
    with subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE, text=True) as proc:
        assert proc.stdout.readline().strip() == "go"
        proc.kill()
    with CalibrationStore(path) as store:
        history = store.history("a")
        assert len(history) >= 20
        offsets = [r.calibration.offset[0] for r in history]
        assert offsets == sorted(offsets, reverse=True) and offsets[-1] == 1
        for record in history:
            assert wire.calibration_from_record(record.to_record()).id == record.id


def test_rows_failing_the_entry_check_are_skipped_counted_and_the_rest_served(tmp_path):
    path = tmp_path / "c.db"
    with CalibrationStore(path) as store:
        assert store.save(_record("a", [1, 0, 0], 1))
        assert store.save(_record("b", [5, 0, 0], 1))
    reflected = {**_record("a", [2, 0, 0], 2).to_record(), "matrix": [[-1, 0, 0], [0, 1, 0], [0, 0, 1]]}
    singular = {**_record("b", [6, 0, 0], 2).to_record(), "matrix": [[1, 0, 0], [0, 1, 0], [0, 0, 1e-9]]}
    with sqlite3.connect(path) as db:  # rows written by something else: a forged record and an unreadable one
        for record in (reflected, singular):
            db.execute(
                "INSERT INTO calibrations (device, id, created_ns, record) VALUES (?, ?, ?, ?)",
                (record["device"], record["id"], 2, json.dumps(record)),
            )
        db.execute("INSERT INTO calibrations (device, id, created_ns, record) VALUES ('a', 'x', 3, '{not json')")
    with CalibrationStore(path) as store:  # as a calibrator on restart reads it
        latest = store.all_latest()
        assert {d: r.calibration.offset[0] for d, r in latest.items()} == {"a": 1, "b": 5}
        assert store.latest("a").calibration.offset[0] == 1 and len(store.history("a")) == 1
        assert store.skipped_rows >= 3
