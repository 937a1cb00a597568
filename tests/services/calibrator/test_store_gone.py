"""The database deleted or replaced under a running calibrator (issue 32 C): the store notices (the device and inode
at its path against the ones it opened, and the file's header) before acknowledging a write, acknowledges nothing
more, and the calibrator's status and its session replies say why; nothing from the network ends it."""

from __future__ import annotations

import os
import sqlite3

import numpy as np
import pytest
from helpers import NO_SCOUT, connect_args, free_ports, listen_args, magnet_json, wait_for

from magnet import wire
from magnet.model import Calibration
from services.calibrator.service import Calibrator, CalibratorSettings
from services.calibrator.store import CalibrationStore, StoreError

CAL = Calibration("ellipsoid", [1.0, 0.0, 0.0], np.eye(3))


def _record(device, created_ns=1):
    return wire.DeviceCalibration(device, created_ns, CAL.replace(offset=np.array([float(created_ns), 0.0, 0.0])))


def _delete(path):
    for suffix in ("", "-wal", "-shm"):
        path.with_name(path.name + suffix).unlink(missing_ok=True)


def _replace(path):
    other = path.with_name("other.db")
    with sqlite3.connect(other) as db:
        db.execute("CREATE TABLE t (x)")
    os.replace(other, path)


def _empty(path):
    with open(path, "r+b") as handle:
        handle.truncate(0)


def _overwrite_header(path):
    with open(path, "r+b") as handle:
        handle.write(b"not a database!!")


@pytest.mark.parametrize(
    ("damage", "said"),
    [
        (_delete, "was deleted"),
        (_replace, "was replaced"),
        (_overwrite_header, "no longer starts with an SQLite header"),
        (_empty, "no longer starts with an SQLite header"),
    ],
)
def test_a_store_whose_file_is_deleted_or_replaced_acknowledges_nothing_more(tmp_path, damage, said):
    path = tmp_path / "c.db"
    with CalibrationStore(path) as store:
        assert store.save(_record("a", 1))
        damage(path)
        with pytest.raises(StoreError, match=f"{path} {said}.*restart the calibrator"):
            store.save(_record("a", 2))
        assert said in str(getattr(store, "gone", None))
        with pytest.raises(StoreError):  # gone for good, and an OSError like every store failure
            store.load_rows([])
        assert [r.created_ns for r in store.history("a")] == [1], "the write was not acknowledged, nor stored"
    if damage is not _delete:
        return
    with CalibrationStore(path) as again:  # what a restart finds: nothing acknowledged after the delete is missing
        assert again.count() == 0


def test_the_calibrator_says_its_store_is_gone_and_refuses_sessions_with_the_reason(tmp_path):
    path = tmp_path / "c.db"
    with CalibrationStore(path) as store:
        calibrator = Calibrator(store, CalibratorSettings(), lambda *a: None)
        store.save(_record("a", 1))
        assert calibrator.status("c").to_dict().get("store") == "ok"
        _delete(path)
        for action in ("start", "commit"):
            reply = calibrator.session("a", action, None)
            assert not reply["ok"] and "was deleted" in reply["message"], reply
        status = calibrator.status("c").to_dict()
        assert status["store"] == "gone" and "was deleted" in status["store_problem"]
        reply = calibrator.rollback("a", None, "op")
        assert not reply["ok"] and "was deleted" in reply["message"], reply


@pytest.mark.integration
def test_a_running_calibrator_whose_database_is_deleted_refuses_a_commit_with_the_reason(tmp_path, procs):
    path = tmp_path / "c.db"
    (port,) = free_ports(1)
    procs.start("calibrator", "calibrator", "--db", str(path), *listen_args(port))
    remote = [*NO_SCOUT, *connect_args(port), "--timeout", "2"]

    def status():
        code, lines = magnet_json("get", "status", "calibrator", *remote)
        return lines[0] if code == 0 and lines else None

    wait_for(status, 30, "the calibrator's status")
    _delete(path)
    wait_for(lambda: "was deleted" in procs.log("calibrator"), 10, "the calibrator to log it on its own")
    code, [reply] = magnet_json("calibrate", "d1", "commit", *remote)
    assert code != 0 and not reply["ok"] and "was deleted" in reply["message"], reply
    now = status()
    assert now is not None and now["store"] == "gone" and "was deleted" in now["store_problem"], now
    assert procs.alive("calibrator"), "nothing from the network ends the service"
