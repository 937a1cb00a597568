"""Every calibrator gone (killed -9): the compass keeps applying the record in force it holds to new raw batches and
its status says the calibrators are gone, since when."""

from __future__ import annotations

import json
import os
import signal
import time

import numpy as np
import pytest
import zenoh
from helpers import NO_SCOUT, connect_args, emulated_edge, free_ports, listen_args, magnet_json, wait_for

from magnet import wire
from magnet.model import Calibration
from services.calibrator.store import CalibrationStore

pytestmark = pytest.mark.integration


def _status(name, port):
    code, lines = magnet_json("get", "status", name, *NO_SCOUT, *connect_args(port), "--timeout", "2", timeout=60)
    return lines[0] if code == 0 and lines else None


def test_the_compass_keeps_the_record_in_force_when_every_calibrator_is_gone(procs, tmp_path):
    record = wire.DeviceCalibration(
        "kept", time.time_ns(), Calibration("ellipsoid", np.array([12.0, -7.0, 4.0]), np.eye(3))
    )
    with CalibrationStore(tmp_path / "c.db") as store:
        store.save(record)
    cal_port, comp_port, edge_port = free_ports(3)
    procs.start("calibrator", "calibrator", "--db", str(tmp_path / "c.db"), *listen_args(cal_port))
    procs.start("compass", "compass", *listen_args(comp_port), *connect_args(cal_port))
    wait_for(
        lambda: (s := _status("compass", comp_port)) and s["calibrations"] == 1 and s["calibrators_state"] == "present",
        60,  # each look is a `magnet get status` process: under a loaded CI run they took over 30 s in all
        "the compass to hold the record and see the calibrator",
    )
    os.kill(procs.procs["calibrator"].pid, signal.SIGKILL)
    procs.procs["calibrator"].wait()
    gone = wait_for(
        lambda: (s := _status("compass", comp_port)) and s["calibrators_state"] == "gone" and s,
        20,
        "the compass to see it go",
    )
    assert gone["calibrations"] == 1 and gone["calibrators"] == 0 and gone["calibrators_gone_since_ns"] > 0
    conf = zenoh.Config()
    conf.insert_json5("connect/endpoints", json.dumps([f"tcp/127.0.0.1:{comp_port}"]))
    conf.insert_json5("scouting/multicast/enabled", "false")
    with zenoh.open(conf) as session, session.declare_subscriber("magnet/kept/heading") as headings:
        procs.start("edge", *emulated_edge("kept", 100, 10), *listen_args(edge_port), *connect_args(comp_port))
        batch = wire.decode_heading(wait_for(lambda: headings.try_recv(), 30, "a heading").payload.to_bytes())
    assert batch.calibration_id == record.id, "the record in force is applied with no calibrator left"
