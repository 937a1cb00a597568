"""``magnet edge --ros2``: a ROS 2 robot's MagneticField + Imu, published by a peer nobody here wrote
(zenoh-ros2-sdk, its own process, offline, on 127.0.0.1 with scouting off) from the simulator, is a source the
pipeline turns into calibrated headings. Bad input on the way (malformed CDR, an Imu on the MagneticField key, a
flood of liveliness tokens under ``@ros2_lv``) is dropped and counted; nothing ends."""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest
import zenoh
from helpers import NO_SCOUT, REPO_ROOT, connect_args, listen_args, magnet_json, wait_for

from magnet.ros2 import messages, names

pytestmark = pytest.mark.integration

# -P: the script's folder (tests/, holding tests/magnet/) must not stand in for the magnet package
CLIENT = [
    sys.executable,
    "-P",
    str(REPO_ROOT / "tests" / "ros2_sdk_client.py"),
]
DEVICE = "robot-1"


def status(port: int) -> dict | None:
    code, lines = magnet_json("get", "status", f"edge-{DEVICE}", *NO_SCOUT, *connect_args(port), "--timeout", "2")
    return lines[0] if code == 0 and lines else None


def calibration(port: int) -> dict | None:
    code, lines = magnet_json("get", "calibration", DEVICE, *NO_SCOUT, *connect_args(port), "--timeout", "2")
    return lines[0] if code == 0 and lines else None


def hostile(port: int) -> None:
    """Garbage and a mistyped message on the robot's MagneticField key, and 2000 liveliness tokens in the graph."""
    conf = zenoh.Config()
    conf.insert_json5("connect/endpoints", json.dumps([f"tcp/127.0.0.1:{port}"]))
    conf.insert_json5("scouting/multicast/enabled", "false")
    key = names.topic_key(0, "/robot/mag", messages.MAGNETIC_FIELD, messages.type_hash(messages.MAGNETIC_FIELD))
    imu = messages.imu_cdr(np.array([1]), "x", np.array([[0, 0, 0, 1.0]]), None, None)[0]
    with zenoh.open(conf) as session:
        for payload in (b"", b"\x00\x01\x00\x00garbage", b"\xff" * 300, imu, imu[:40]):
            session.put(key, payload)
        tokens = [
            session.liveliness().declare_token(
                f"@ros2_lv/0/{i:x}/0/{i}/MP/%/%/flood/%robot%mag/junk/RIHS01_x/::,1:,:,:,,"
            )
            for i in range(2000)
        ]
        for token in tokens:
            token.undeclare()


def test_a_ros2_robots_field_and_imu_become_calibrated_headings(procs, tmp_path):
    cal_port, comp_port, edge_port = procs.start_services()
    procs.start(
        "edge",
        "edge",
        "--ros2",
        "--mag-topic",
        "/robot/mag",
        "--imu-topic",
        "/robot/imu",
        "--device",
        DEVICE,
        "--batch",
        "10",
        *listen_args(edge_port),
        *connect_args(cal_port, comp_port),
    )
    wait_for(lambda: status(edge_port), 20, "the edge's status")
    robot_log = open(tmp_path / "robot.log", "w")  # noqa: SIM115 (closed in finally)
    robot = subprocess.Popen(
        [*CLIENT, str(edge_port), "publish", "robot", "120", "100"],
        stdout=robot_log,
        stderr=subprocess.STDOUT,
        cwd=REPO_ROOT,
    )
    try:
        wait_for(lambda: (s := status(edge_port)) and s["published_samples"] > 200, 30, "samples from ROS 2")
        hostile(edge_port)
        cal = wait_for(lambda: calibration(cal_port), 60, "a calibration of the robot's magnetometer")
        code, lines = magnet_json(
            "watch", "heading", DEVICE, "--count", "3", *NO_SCOUT, *connect_args(comp_port), timeout=20
        )
    finally:
        robot.terminate()
        robot.wait(timeout=10)
        robot_log.close()
    assert code == 0 and lines, "headings from the ROS 2 source"
    assert all(h["calibration_id"] == cal["id"] for h in lines)
    assert all(h["flags"] for h in lines)  # calibrated (and fused: the Imu carries rates)
    edge = wait_for(lambda: status(edge_port), 10, "the edge's status")
    causes = edge["reads"]["errors_by_cause"]
    assert causes.get("malformed-MagneticField", 0) == 5, causes
    assert edge["reads"]["samples"] > 200 and edge["sensor"] == "ros2"
    assert procs.alive("edge") and procs.alive("compass") and procs.alive("calibrator")
