"""``magnet calibrator --method gyro-ellipsoid`` against an emulated 9-axis chip (icm20948) on loopback: the
calibrator collects consecutive runs with the gyroscope, fits them, and stores and serves a gyro-ellipsoid record
that finds the simulated hard iron."""

from __future__ import annotations

import json

import numpy as np
import pytest
from helpers import NO_SCOUT, connect_args, free_ports, listen_args, magnet_json, wait_for

pytestmark = pytest.mark.integration

DEVICE = "gyro-1"
PLAIN = "plain-1"
HARD_IRON_UT = (12.0, -7.0, 4.0)


def _status(port):
    code, lines = magnet_json("get", "status", "calibrator", *NO_SCOUT, *connect_args(port), "--timeout", "2")
    return lines[0] if code == 0 and lines else None


def test_the_calibrator_fits_an_emulated_gyroscope_edge_with_gyro_ellipsoid(procs, tmp_path):
    cal_port, edge_port, plain_port = free_ports(3)
    procs.start(
        "calibrator", "calibrator", "--method", "gyro-ellipsoid", "--db", str(tmp_path / "c.db"), *listen_args(cal_port)
    )
    wait_for(lambda: _status(cal_port), 30, "the calibrator to answer")
    procs.start(
        "edge",
        *("edge", "--device", DEVICE, "--sensor", "icm20948", "--emulate", "--trajectory", "tumble"),
        *("--hard-iron", ",".join(map(str, HARD_IRON_UT)), "--rate", "100", "--batch", "10"),
        *("--trajectory-samples", "3000"),
        *listen_args(edge_port),
        *connect_args(cal_port),
    )
    # a magnetometer alone (the simulator's still tumble sends no gyroscope): counted and explained, never fitted
    procs.start(
        "plain",
        *("edge", "--device", PLAIN, "--sensor", "sim", "--emulate", "--trajectory", "tumble", "--hard-iron", "5,5,5"),
        *listen_args(plain_port),
        *connect_args(cal_port),
    )

    def served():
        code, lines = magnet_json("get", "calibration", DEVICE, *NO_SCOUT, *connect_args(cal_port), "--timeout", "2")
        return code == 0 and lines and lines[0]

    record = wait_for(served, 90, "a gyro-ellipsoid calibration served")
    assert record["method"] == "gyro-ellipsoid" and record["accepted"]
    np.testing.assert_allclose(record["offset"], HARD_IRON_UT, atol=1.0)  # uT, the first accepted fit
    status = wait_for(lambda: (s := _status(cal_port)) and s["no_gyroscope"] > 0 and s, 30, "a plain batch counted")
    assert status["stored"] == 1 and status["fits"] >= 1
    code, lines = magnet_json(
        "calibrate", PLAIN, "status", "--json", *NO_SCOUT, *connect_args(cal_port), "--timeout", "2"
    )
    assert code == 0 and "gyro-ellipsoid needs a gyroscope" in json.dumps(lines), lines
    # a session may choose auto (the default of magnet fit and of the calibrator): the plain device's batches then
    # go to its sphere cells and are no longer counted as missing a gyroscope
    code, lines = magnet_json(
        "calibrate", PLAIN, "start", "--method", "auto", "--json", *NO_SCOUT, *connect_args(cal_port), "--timeout", "2"
    )
    assert code == 0 and lines[0]["ok"] and "auto" in lines[0]["message"], lines
    code, lines = magnet_json(
        "calibrate", PLAIN, "status", "--json", *NO_SCOUT, *connect_args(cal_port), "--timeout", "2"
    )
    assert code == 0 and "gyro-ellipsoid needs a gyroscope" not in json.dumps(lines), lines
