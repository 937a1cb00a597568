"""``magnet compass --ros2`` seen by a ROS 2 peer nobody here wrote (zenoh-ros2-sdk, its own process, offline, on
127.0.0.1 with scouting off): its subscriber decodes magnet's MagneticField and Imu, whose values are magnet's own
heading messages after the REP-103 frame conversion; its topic list (the graph from liveliness) shows magnet's topics
with their types."""

from __future__ import annotations

import json
import subprocess
import sys
import threading

import numpy as np
import pytest
import zenoh
from helpers import REPO_ROOT, connect_args, free_ports, listen_args, wait_for

from magnet import wire
from magnet.frames import euler_to_quaternion, quaternion_to_matrix
from magnet.ros2.names import ros_name_of_device

pytestmark = pytest.mark.integration

# -P: the script's folder (tests/, holding tests/magnet/) must not stand in for the magnet package
CLIENT = [
    sys.executable,
    "-P",
    str(REPO_ROOT / "tests" / "ros2_sdk_client.py"),
]
DEVICE = "imu-000"  # not a valid ROS name as it is: mapped to ximu_2d000


def sdk(port: int, *args: str, timeout: float = 60) -> list:
    out = subprocess.run([*CLIENT, str(port), *args], capture_output=True, text=True, timeout=timeout, cwd=REPO_ROOT)
    assert out.returncode == 0, out.stderr[-3000:]
    return [json.loads(line) for line in out.stdout.splitlines() if line.startswith(("{", "["))]


def start_compass_and_fleet(procs, comp_port: int, edge_port: int) -> None:
    procs.start("compass", "compass", "--ros2", *listen_args(comp_port))
    procs.start(
        "edge",
        "edge",
        "--emulate",
        "--devices",
        "1",
        "--device",
        "imu",
        "--gyro",
        "--rate",
        "50",
        "--batch",
        "5",
        *listen_args(edge_port),
        *connect_args(comp_port),
    )


def collect_headings(port: int, stop: threading.Event, into: dict[int, tuple], device: str = DEVICE) -> None:
    """magnet's own heading messages of ``device``, by sample time: (field_ut, true heading, pitch, roll, quat)."""
    conf = zenoh.Config()
    conf.insert_json5("connect/endpoints", json.dumps([f"tcp/127.0.0.1:{port}"]))
    conf.insert_json5("scouting/multicast/enabled", "false")
    with zenoh.open(conf) as session:
        sub = session.declare_subscriber(f"magnet/{device}/heading", zenoh.handlers.FifoChannel(4096))
        while not stop.is_set():
            sample = sub.try_recv()
            if sample is None:
                stop.wait(0.01)
                continue
            h = wire.decode_heading(sample.payload.to_bytes())
            for i, t in enumerate(h.t_ns.tolist()):
                quat = h.quat_wxyz[i] if h.quat_wxyz is not None else None
                into[t] = (h.field_ut[i], h.true_heading_deg[i], h.pitch_deg[i], h.roll_deg[i], quat)


def stamp_ns(msg: dict) -> int:
    return msg["header"]["stamp"]["sec"] * 1_000_000_000 + msg["header"]["stamp"]["nanosec"]


def test_a_ros2_peer_decodes_magnets_field_and_attitude_and_sees_its_topics(procs):
    comp_port, edge_port = free_ports(2)
    start_compass_and_fleet(procs, comp_port, edge_port)
    headings: dict[int, tuple] = {}
    stop = threading.Event()
    watcher = threading.Thread(target=collect_headings, args=(comp_port, stop, headings), daemon=True)
    watcher.start()
    try:
        wait_for(lambda: len(headings) > 10, 30, "magnet's own headings")
        name = ros_name_of_device(DEVICE)
        mags = sdk(comp_port, "subscribe", f"/magnet/{name}/mag", "sensor_msgs/msg/MagneticField", "20", "20")
        imus = sdk(comp_port, "subscribe", f"/magnet/{name}/imu", "sensor_msgs/msg/Imu", "20", "20")
        graph = dict(sdk(comp_port, "topics")[0])
        diagnostics = sdk(comp_port, "subscribe", "/diagnostics", "diagnostic_msgs/msg/DiagnosticArray", "1", "15")
        wait_for(lambda: all(stamp_ns(m) in headings for m in mags + imus), 10, "the headings of those samples")
    finally:
        stop.set()
        watcher.join(timeout=10)
    assert len(mags) == 20 and len(imus) == 20
    for msg in mags:
        field_ut = headings[stamp_ns(msg)][0]
        got = msg["magnetic_field"]
        # magnet's heading message carries float32: REP-103 FLU is (x, -y, -z), tesla
        np.testing.assert_allclose(
            [got["x"], got["y"], got["z"]], field_ut * np.array([1, -1, -1]) * 1e-6, rtol=1e-6, atol=1e-12
        )
        assert msg["header"]["frame_id"] == name
    for msg in imus:
        _, true_heading, pitch, roll, quat = headings[stamp_ns(msg)]
        q = msg["orientation"]
        ros = quaternion_to_matrix(np.array([q["w"], q["x"], q["y"], q["z"]]))  # body FLU -> ENU
        ours = quaternion_to_matrix(quat if quat is not None else euler_to_quaternion(true_heading, pitch, roll))
        flu_to_frd, ned_to_enu = np.diag([1.0, -1.0, -1.0]), np.array([[0, 1, 0], [1, 0, 0], [0, 0, -1.0]])
        np.testing.assert_allclose(ros, ned_to_enu @ ours @ flu_to_frd, atol=1e-5)
        assert msg["angular_velocity_covariance"][0] == 0 and msg["linear_acceleration_covariance"][0] == 0
        acc = msg["linear_acceleration"]
        up = ros @ np.array([acc["x"], acc["y"], acc["z"]])  # the specific force in ENU: gravity's reaction, up
        assert up[2] > 8.0 and np.hypot(up[0], up[1]) < 2.0, up
    assert graph[f"/magnet/{name}/mag"] == ["sensor_msgs/msg/MagneticField"]
    assert graph[f"/magnet/{name}/imu"] == ["sensor_msgs/msg/Imu"]
    assert graph["/diagnostics"] == ["diagnostic_msgs/msg/DiagnosticArray"]
    (status,) = diagnostics[0]["status"]  # one device, not calibrated (no calibrator here): WARN
    assert status["hardware_id"] == DEVICE and status["level"] == 1 and "not calibrated" in status["message"]
    assert {v["key"]: v["value"] for v in status["values"]}["calibrated"] == "false"
    assert procs.alive("compass"), procs.log("compass")[-2000:]
