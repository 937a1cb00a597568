"""The services end to end, each in its own process on loopback (explicit ports, no multicast), bounded in time.

- an emulated LSM303DLH with known hard and soft iron -> the calibrator accepts a calibration whose offset is within
  1 uT of the truth -> the compass's true heading agrees with the simulator's truth -> another process queries the
  coefficients and the history;
- kill -9 of the calibrator, restart: the stored calibration is served again; compass restart picks it up; garbage
  on the raw and calibration keys is counted and everything keeps serving.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys

import numpy as np
import pytest
from helpers import (
    MAGNET,
    NO_SCOUT,
    connect_args,
    free_ports,
    listen_args,
    liveliness_keys,
    magnet_json,
    wait_for,
    wait_for_liveliness,
)

from magnet.attitude.heading import angle_difference_deg

HARD_IRON = np.array([25.0, -15.0, 10.0])
SOFT_IRON = "1.10,0.05,0,0.05,0.92,0.02,0,0.02,1.0"
LOCATION = "50.45,30.52"

pytestmark = pytest.mark.integration


def get_calibration(device, port):
    code, lines = magnet_json("get", "calibration", device, *NO_SCOUT, *connect_args(port), "--timeout", "2")
    return lines[0] if code == 0 and lines else None


def get_status(service, port):
    code, lines = magnet_json("get", "status", service, *NO_SCOUT, *connect_args(port), "--timeout", "2")
    return lines[0] if code == 0 and lines else None


def start_pipeline(procs, tmp_path, device, sensor, cal_port, comp_port, edge_port):
    procs.start("calibrator", "calibrator", "--db", str(tmp_path / "cal.db"), *listen_args(cal_port))
    procs.start("compass", "compass", "--location", LOCATION, *listen_args(comp_port), *connect_args(cal_port))
    procs.start(
        "edge",
        "edge",
        "--device",
        device,
        "--sensor",
        sensor,
        "--emulate",
        "--rate",
        "500",
        "--batch",
        "25",
        "--hard-iron",
        ",".join(map(str, HARD_IRON)),
        "--soft-iron",
        SOFT_IRON,
        "--location",
        LOCATION,
        "--trajectory-samples",
        "2000",
        *listen_args(edge_port),
        *connect_args(cal_port, comp_port),
    )


def test_emulated_lsm303dlh_is_calibrated_and_headings_match_the_truth(procs, tmp_path):
    cal_port, comp_port, edge_port = free_ports(3)
    start_pipeline(procs, tmp_path, "lsm-1", "lsm303dlh", cal_port, comp_port, edge_port)
    record = wait_for(lambda: get_calibration("lsm-1", cal_port), 40, "an accepted calibration")
    assert record["accepted"] and record["device"] == "lsm-1" and record["method"] == "ellipsoid"
    offset_error = np.abs(np.array(record["offset"]) - HARD_IRON).max()
    assert offset_error < 1.0, f"offset {record['offset']} vs hard iron {HARD_IRON}"

    # headings and raw batches (which carry the simulator's truth) of the same batches, joined by seq
    watch = [*NO_SCOUT, "--count", "60"]
    headings = subprocess.Popen(
        [*MAGNET, "watch", "heading", "lsm-1", *watch, *connect_args(comp_port)], stdout=subprocess.PIPE, text=True
    )
    raws = subprocess.Popen(
        [*MAGNET, "watch", "raw", "lsm-1", *watch, *connect_args(edge_port)], stdout=subprocess.PIPE, text=True
    )
    heading_out, _ = headings.communicate(timeout=30)
    raw_out, _ = raws.communicate(timeout=30)
    by_seq = {m["seq"]: m for m in map(json.loads, raw_out.splitlines())}
    errors = []
    for message in map(json.loads, heading_out.splitlines()):
        raw = by_seq.get(message["seq"])
        if raw is None or message["calibration_id"] != record["id"]:
            continue
        assert all(f & 1 for f in message["flags"]), "CALIBRATED flag set on calibrated headings"
        pitch = np.array(raw["truth"]["pitch_deg"])
        usable = np.abs(pitch) < 70  # near vertical the heading of the x axis is undefined
        errors += list(
            angle_difference_deg(np.array(message["true_heading_deg"]), np.array(raw["truth"]["heading_deg"]))[usable]
        )
    assert len(errors) > 200, f"only {len(errors)} comparable samples"
    rms = float(np.sqrt(np.mean(np.square(errors))))
    print(f"true heading RMS error {rms:.3f} deg over {len(errors)} samples")
    assert rms < 2.0, f"true heading RMS error {rms:.2f} deg"

    code, lines = magnet_json("get", "calibration", "lsm-1", "--history", *NO_SCOUT, *connect_args(cal_port))
    assert code == 0 and lines[0]["records"][0]["id"] == record["id"]
    assert lines[0]["records"][0]["matrix"] == record["matrix"]


GARBAGE = r"""
import sys, threading, msgpack, zenoh
conf = zenoh.Config()
conf.insert_json5("connect/endpoints", '["tcp/127.0.0.1:%s", "tcp/127.0.0.1:%s"]' % (sys.argv[1], sys.argv[2]))
conf.insert_json5("scouting/multicast/enabled", "false")
good = {"v": 1, "device": "g-1", "seq": 0, "sensor": "x", "t_ns": [1], "mag_ut": [[1.0, 2.0, 3.0]]}
payloads = [b"\xc1not msgpack", msgpack.packb([1, 2]), msgpack.packb({**good, "v": 9}),
            msgpack.packb({**good, "mag_ut": [[float("nan"), 0.0, 0.0]]}),
            msgpack.packb({**good, "mag_ut": [[1e9, 0, 0]]}), msgpack.packb({**good, "mag_ut": [[1.0, 2.0]]}),
            msgpack.packb({**good, "device": "other"}), b"\x00" * 5_000_000]
services = {"magnet/@alive/compass/compass", "magnet/@alive/calibrator/calibrator"}
seen, reachable = set(), threading.Event()


def on_token(sample):
    seen.add(str(sample.key_expr))
    if services <= seen:
        reachable.set()


with zenoh.open(conf) as session:
    # connected to both services (their tokens, like their subscribers, arrive once the link is up) before putting
    session.liveliness().declare_subscriber("magnet/@alive/**", on_token, history=True)
    assert reachable.wait(20), f"compass and calibrator not reachable: {seen}"
    for payload in payloads:
        session.put("magnet/g-1/raw", payload)
        session.put("magnet/g-1/calibration", payload)
    session.put("magnet/g-1/calibration", msgpack.packb({"v": 1, "device": "g-1", "offset": [0, 0], "matrix": [[1]]}))
    replies = list(session.get("magnet/@status/*", timeout=5))  # answered after the puts on the same links
"""


def test_restarts_keep_calibrations_and_garbage_is_counted(procs, tmp_path):
    cal_port, comp_port, edge_port, cal2_port, comp2_port = free_ports(5)
    start_pipeline(procs, tmp_path, "sim-1", "sim", cal_port, comp_port, edge_port)
    first = wait_for(lambda: get_calibration("sim-1", cal_port), 40, "an accepted calibration")

    os.kill(procs.procs["calibrator"].pid, signal.SIGKILL)
    procs.procs["calibrator"].wait()
    procs.start(
        "calibrator2",
        "calibrator",
        "--db",
        str(tmp_path / "cal.db"),
        *listen_args(cal2_port),
        *connect_args(comp_port, edge_port),
    )
    again = wait_for(lambda: get_calibration("sim-1", cal2_port), 20, "the stored calibration after kill -9")
    assert again == first

    procs.procs["compass"].send_signal(signal.SIGTERM)
    assert procs.procs["compass"].wait(timeout=10) == 0, "compass stops cleanly on SIGTERM"
    procs.start(
        "compass2", "compass", "--location", LOCATION, *listen_args(comp2_port), *connect_args(cal2_port, edge_port)
    )
    wait_for(
        lambda: (s := get_status("compass", comp2_port)) and s["calibrations"] == 1 and s,
        20,
        "the restarted compass to hold the calibration",
    )
    code, lines = magnet_json("watch", "heading", "sim-1", "--count", "3", *NO_SCOUT, *connect_args(comp2_port))
    assert code == 0 and all(m["calibration_id"] == first["id"] for m in lines)

    subprocess.run([sys.executable, "-c", GARBAGE, str(comp2_port), str(cal2_port)], check=True, timeout=30)
    compass_status = wait_for(
        lambda: (s := get_status("compass", comp2_port)) and s["dropped_total"] >= 15 and s,
        10,
        "the compass to count the garbage",
    )
    calibrator_status = get_status("calibrator", cal2_port)
    print("compass drops", compass_status["dropped"], "calibrator drops", calibrator_status["dropped"])
    assert calibrator_status["dropped_total"] >= 7, calibrator_status
    assert {"raw:not-msgpack", "raw:wrong-version", "raw:non-finite", "calibration:bad-calibration"} <= set(
        compass_status["dropped"]
    )
    assert compass_status["calibrations"] == 1, "garbage changed no calibration"
    assert get_calibration("sim-1", cal2_port) == first
    code, lines = magnet_json("watch", "heading", "sim-1", "--count", "2", *NO_SCOUT, *connect_args(comp2_port))
    assert code == 0 and len(lines) == 2, "the compass keeps serving"
    assert procs.alive("calibrator2") and procs.alive("compass2") and procs.alive("edge")


def test_liveliness_tokens_name_every_service_and_device_and_vanish_with_a_killed_process(procs, tmp_path):
    cal_port, comp_port, edge_port = free_ports(3)
    start_pipeline(procs, tmp_path, "live-1", "sim", cal_port, comp_port, edge_port)
    wanted = {
        "magnet/@alive/calibrator/calibrator",
        "magnet/@alive/compass/compass",
        "magnet/@alive/device/live-1",
        "magnet/@alive/edge/live-1",
    }  # tokens may arrive in any order: wait for every one
    wait_for_liveliness(comp_port, wanted)
    os.kill(procs.procs["calibrator"].pid, signal.SIGKILL)
    procs.procs["calibrator"].wait()
    wait_for(
        lambda: "magnet/@alive/calibrator/calibrator" not in liveliness_keys(comp_port),
        10,
        "the killed calibrator's token to vanish",
    )
    assert "magnet/@alive/compass/compass" in liveliness_keys(comp_port)


def test_operator_calibration_session_over_the_network(procs, tmp_path):
    cal_port, edge_port = free_ports(2)
    procs.start("calibrator", "calibrator", "--db", str(tmp_path / "op.db"), "--no-auto", *listen_args(cal_port))
    procs.start(
        "edge",
        "edge",
        "--device",
        "op-1",
        "--sensor",
        "lsm303dlh",
        "--emulate",
        "--rate",
        "500",
        "--batch",
        "25",
        "--hard-iron",
        ",".join(map(str, HARD_IRON)),
        *listen_args(edge_port),
        *connect_args(cal_port),
    )
    remote = [*NO_SCOUT, *connect_args(cal_port)]
    wait_for(
        lambda: (s := get_status("calibrator", cal_port)) and s["received_batches"] > 0,
        20,
        "the calibrator to receive the device's samples",
    )
    code, [idle] = magnet_json("calibrate", "op-1", "status", *remote)
    assert code == 0 and idle["state"] == "idle"
    code, [started] = magnet_json("calibrate", "op-1", "start", "--method", "ellipsoid+align", *remote)
    assert code == 0 and started["ok"] and started["progress"]["method"] == "ellipsoid+align"
    ready = wait_for(
        lambda: (s := magnet_json("calibrate", "op-1", "status", *remote)[1][0])["progress"].get("accepted") and s,
        40,
        "the session's fit to pass the gate",
    )
    assert ready["state"] == "session" and get_calibration("op-1", cal_port) is None, "nothing stored before commit"
    code, [committed] = magnet_json("calibrate", "op-1", "commit", *remote)
    assert code == 0 and committed["ok"]
    stored = get_calibration("op-1", cal_port)
    assert stored["id"] == committed["calibration"]["id"] and stored["method"] == "ellipsoid+align"
    assert np.abs(np.array(stored["offset"]) - HARD_IRON).max() < 1.0
