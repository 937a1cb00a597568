"""Trust starts at the fit, with real processes on loopback (a router, a calibrator, a compass with --trust, an edge):
a row written into the calibration database by hand is served as stored after a calibrator restart and refused by
the compass (counted); a trusted record whose created_ns lies far in the future does not block a genuine newer one."""

from __future__ import annotations

import json
import sqlite3
import time

import numpy as np
import pytest
from helpers import NO_SCOUT, free_ports, magnet_json, run_magnet, wait_for

from magnet import signing, wire
from magnet.model import Calibration
from services.calibrator.service import Calibrator, CalibratorSettings
from services.calibrator.store import CalibrationStore

pytestmark = pytest.mark.integration

DEVICE = "trust-1"
GENUINE = Calibration(
    "ellipsoid", [10.0, -5.0, 2.0], np.diag([1.05, 0.95, 1.0]), field_strength=50, quality={"coverage": 0.9}
)
PLANTED = GENUINE.replace(offset=np.array([40.0, 0.0, 0.0]))
FAR_FUTURE_NS = 4_000_000_000 * 10**9  # the year 2096


class Pipeline:
    """A router on a free port; calibrator, compass (trusting one key), edge and viewers as its clients."""

    def __init__(self, procs, tmp_path):
        self.procs, self.tmp_path = procs, tmp_path
        (self.port,) = free_ports(1)
        self.db = tmp_path / "cal.db"
        self.key, self.pub = tmp_path / "signing/cal.key", tmp_path / "signing/cal.pub"
        made = run_magnet("keys", "--out", str(tmp_path / "signing"), "--name", "cal")
        assert made.returncode == 0, made.stderr
        self.signer = signing.Signer(signing.load_private_key(self.key.read_bytes()))

    def client(self):
        return ["--mode", "client", *NO_SCOUT, "--connect", f"tcp/127.0.0.1:{self.port}"]

    def start(self):
        self.procs.start("router", "router", *NO_SCOUT, "--listen", f"tcp/127.0.0.1:{self.port}")
        self.start_calibrator()
        self.procs.start("compass", "compass", "--trust", str(self.pub), "--location", "50.45,30.52", *self.client())
        self.procs.start(
            "edge", "edge", "--device", DEVICE, "--emulate", "--rate", "200", "--batch", "20", *self.client()
        )

    def start_calibrator(self):
        self.procs.start(
            "calibrator", "calibrator", "--db", str(self.db), "--signing-key", str(self.key), *self.client()
        )
        wait_for(lambda: self.status("calibrator"), 30, "the calibrator to answer")

    def stop(self, name):
        self.procs.procs[name].terminate()
        self.procs.procs[name].wait(timeout=10)

    def status(self, name):
        code, lines = magnet_json("get", "status", name, *self.client(), "--timeout", "2", timeout=60)
        return lines[0] if code == 0 and lines else None

    def heading_calibration(self):
        code, lines = magnet_json("watch", "heading", DEVICE, "--count", "1", *self.client(), timeout=60)
        return lines[0].get("calibration_id") if code == 0 and lines else "no heading"

    def wait_heading_calibration(self, calibration_id, what):
        return wait_for(lambda: self.heading_calibration() == calibration_id, 60, what)


def _genuine_store(pipeline, *calibrations):
    """The database as the calibrator makes it: each calibration committed (numbered, signed when made)."""
    with CalibrationStore(pipeline.db) as store:
        calibrator = Calibrator(store, CalibratorSettings(), lambda *a: None, signer=pipeline.signer)
        return [calibrator.commit(DEVICE, calibration) for calibration in calibrations]


def test_a_row_inserted_by_hand_is_not_applied_by_a_trusting_compass_after_a_calibrator_restart(procs, tmp_path):
    pipeline = Pipeline(procs, tmp_path)
    (genuine,) = _genuine_store(pipeline, GENUINE)
    pipeline.start()
    pipeline.wait_heading_calibration(genuine.id, "headings with the genuine calibration")

    pipeline.stop("calibrator")
    planted = wire.DeviceCalibration(DEVICE, genuine.created_ns + 1, PLANTED, version=genuine.version + 1)
    copied_signature = {**planted.to_record(), "sig": genuine.sig, "key_id": genuine.key_id}
    with sqlite3.connect(pipeline.db) as db:  # what anyone who can write the file can do
        db.execute(
            "INSERT INTO calibrations (device, id, created_ns, record, version) VALUES (?, ?, ?, ?, ?)",
            (DEVICE, planted.id, planted.created_ns, json.dumps(copied_signature), planted.version),
        )
    pipeline.start_calibrator()

    status = wait_for(
        lambda: (s := pipeline.status("compass")) and s["dropped"].get("calibration:bad-signature") and s,
        30,
        "the compass to refuse the planted record and count it",
    )
    assert pipeline.status("calibrator")["unverified_records"] == 1
    code, served = magnet_json("get", "calibration", DEVICE, *pipeline.client(), "--timeout", "2", timeout=60)
    assert code == 0 and served[0]["id"] == planted.id and served[0]["sig"] == genuine.sig, "served as stored"
    assert all(pipeline.heading_calibration() == genuine.id for _ in range(3)), "the genuine calibration stays"
    print(f"planted row refused: compass dropped {status['dropped']}")

    pipeline.stop("compass")  # a compass starting now asks the calibrator, and refuses what it is given
    procs.start("compass-2", "compass", "--trust", str(pipeline.pub), "--location", "50.45,30.52", *pipeline.client())
    wait_for(
        lambda: (s := pipeline.status("compass")) and s["dropped"].get("calibration:bad-signature"),
        30,
        "the new compass to refuse the planted record",
    )
    assert pipeline.heading_calibration() != planted.id


def test_a_trusted_record_from_the_far_future_does_not_block_a_genuine_newer_one(procs, tmp_path):
    pipeline = Pipeline(procs, tmp_path)
    first, _ = _genuine_store(pipeline, GENUINE, PLANTED)
    with CalibrationStore(pipeline.db) as store:  # the second was made by a calibrator whose clock ran 70 years ahead
        future = wire.DeviceCalibration(DEVICE, FAR_FUTURE_NS, PLANTED, version=2)
        signed = pipeline.signer.sign(future.to_record())
        store._db.execute(
            "UPDATE calibrations SET record = ?, created_ns = ? WHERE version = 2", (json.dumps(signed), FAR_FUTURE_NS)
        )
        assert store.latest(DEVICE).created_ns == FAR_FUTURE_NS
    pipeline.start()
    pipeline.wait_heading_calibration(future.id, "headings with the far-future calibration")

    asked = time.monotonic()
    code, replies = magnet_json("calibrate", DEVICE, "rollback", "--to", first.id, *pipeline.client(), timeout=60)
    assert code == 0 and replies[0]["ok"], replies
    newer = replies[0]["calibration"]
    assert newer["version"] == 3 and newer["created_ns"] < FAR_FUTURE_NS
    pipeline.wait_heading_calibration(first.id, "the genuine newer record (version 3, made now) to be applied")
    applied_s = time.monotonic() - asked
    assert "calibration:stale" not in pipeline.status("compass")["dropped"]
    print(
        f"version 3 (created_ns {newer['created_ns']}) applied over version 2 (created_ns {FAR_FUTURE_NS}) "
        f"{applied_s:.1f} s after the rollback was asked (including the CLI start)"
    )
