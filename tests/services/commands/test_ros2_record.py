"""``magnet record``: a recording of a running pipeline (raw samples, headings, calibrations) reads back with rosbags
message by message, every message of the type its connection names, and the counts are the ones it reports;
Foxglove's MCAP library decodes every message from the file's own schemas; the raw field reads back through
``magnet fit``'s input."""

from __future__ import annotations

import json

import numpy as np
import pytest
from helpers import NO_SCOUT, connect_args, free_ports, listen_args, run_magnet
from rosbags.rosbag2 import Reader
from rosbags.typesys import Stores, get_typestore

from services.common.inputs import InputOptions, read_input

pytestmark = pytest.mark.integration


def test_a_recording_reads_back_message_by_message(procs, tmp_path):
    cal_port, comp_port, edge_port = procs.start_services()
    procs.start(
        "edge",
        "edge",
        "--emulate",
        "--devices",
        "2",
        "--device",
        "rec",
        "--gyro",
        "--rate",
        "50",
        "--batch",
        "10",
        *listen_args(edge_port),
        *connect_args(cal_port, comp_port),
    )
    out = tmp_path / "run.mcap"
    done = run_magnet(
        "record", "--out", str(out), "--seconds", "8", *NO_SCOUT, *connect_args(edge_port, comp_port, cal_port)
    )
    assert done.returncode == 0, done.stderr[-2000:]
    summary = json.loads(done.stdout.strip().splitlines()[-1])
    assert summary["written"]["sensor_msgs/msg/MagneticField"] > 200 and summary["dropped"] == {}
    store = get_typestore(Stores.ROS2_JAZZY)
    counts: dict[str, int] = {}
    with Reader(out) as reader:
        topics = {c.topic: c.msgtype for c in reader.connections}
        for conn, t_ns, data in reader.messages():
            msg = store.deserialize_cdr(data, conn.msgtype)  # each one whole message of its connection's type
            counts[conn.msgtype] = counts.get(conn.msgtype, 0) + 1
            if conn.msgtype != "std_msgs/msg/String":
                assert msg.header.stamp.sec * 10**9 + msg.header.stamp.nanosec == t_ns
    assert counts == summary["written"]
    for device in ("xrec_2d000", "xrec_2d001"):
        assert topics[f"/magnet/{device}/raw/mag"] == "sensor_msgs/msg/MagneticField"
        assert topics[f"/magnet/{device}/raw/imu"] == "sensor_msgs/msg/Imu"
        assert topics[f"/magnet/{device}/mag"] == "sensor_msgs/msg/MagneticField"
        assert topics[f"/magnet/{device}/imu"] == "sensor_msgs/msg/Imu"
    # Foxglove's own MCAP library decodes every message from the schemas in the file (ros2msg), without rosbags
    from mcap.reader import make_reader
    from mcap_ros2.decoder import DecoderFactory

    with out.open("rb") as f:
        decoded = list(make_reader(f, decoder_factories=[DecoderFactory()]).iter_decoded_messages())
    assert len(decoded) == sum(counts.values())
    assert {schema.encoding for schema, _, _, _ in decoded} == {"ros2msg"}
    assert {channel.message_encoding for _, channel, _, _ in decoded} == {"cdr"}
    table = read_input(out, InputOptions(topic="/magnet/xrec_2d000/raw/mag"))
    assert table.acc is not None and "gx" in table.columns
    norms = np.linalg.norm(table.mag, axis=1)
    assert 20 < np.median(norms) < 200  # uT again, simulated field plus hard iron


def test_a_recording_that_hears_nothing_is_an_error_and_leaves_no_bag(tmp_path):
    (port,) = free_ports(1)
    out = tmp_path / "silence.mcap"
    done = run_magnet("record", "--out", str(out), "--seconds", "1", *NO_SCOUT, *listen_args(port))
    assert done.returncode == 1, done.stderr
    assert "heard nothing" in done.stderr and "no bag written" in done.stderr
    assert not out.exists() and not (tmp_path / "silence.mcap.bag").exists()


def test_watching_headings_that_never_come_says_so_and_exits_1():
    (port,) = free_ports(1)
    done = run_magnet("watch", "heading", "--duration", "1", *NO_SCOUT, *listen_args(port))
    assert done.returncode == 1 and "heard no heading on magnet/*/heading" in done.stderr and done.stdout == ""
    quiet = run_magnet("watch", "alert", "--duration", "1", *NO_SCOUT, *listen_args(port))
    assert quiet.returncode == 0 and "heard no alert" in quiet.stderr  # no alert is good news, said all the same
