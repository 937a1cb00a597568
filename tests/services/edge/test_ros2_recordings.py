"""ROS 2 recordings as input: a real recording of ``data/`` (CK-Explorer: accelerometer in g, field in gauss),
written as a rosbag2 by rosbags' own writer in ROS 2's units and frames, gives the same ``magnet fit`` as the CSV;
the bag directory, its bare ``.mcap`` and a ``.db3`` bag all read; a wrong ``--topic`` is one clear line."""

from __future__ import annotations

import json

import numpy as np
import pytest
from rosbags.rosbag2 import StoragePlugin, Writer
from rosbags.typesys import Stores, get_typestore

from services.cli import main
from services.common.inputs import InputOptions, read_input

STORE = get_typestore(Stores.ROS2_JAZZY)
T = STORE.types
G = 9.80665


def write_bag(path, mag_gauss, acc_g, storage=StoragePlugin.MCAP):
    """The samples as MagneticField (tesla) and Imu (m/s^2) in FLU, 100 Hz, by rosbags alone."""
    flip = np.array([1.0, -1.0, -1.0])
    vector, unknown = T["geometry_msgs/msg/Vector3"], np.array([-1.0] + [0.0] * 8)
    with Writer(path, version=9, storage_plugin=storage) as writer:
        mag_conn = writer.add_connection("/ck/mag", "sensor_msgs/msg/MagneticField", typestore=STORE)
        imu_conn = writer.add_connection("/ck/imu", "sensor_msgs/msg/Imu", typestore=STORE)
        for i, (m, a) in enumerate(zip(mag_gauss * 1e-4 * flip, acc_g * G * flip)):
            t_ns = 1_700_000_000_000_000_000 + i * 10_000_000
            header = T["std_msgs/msg/Header"](T["builtin_interfaces/msg/Time"](*divmod(t_ns, 10**9)), "ck")
            mag = T["sensor_msgs/msg/MagneticField"](header, vector(*m), np.zeros(9))
            imu = T["sensor_msgs/msg/Imu"](
                header,
                T["geometry_msgs/msg/Quaternion"](0.0, 0.0, 0.0, 1.0),
                unknown,
                vector(0.0, 0.0, 0.0),
                unknown,
                vector(*a),
                np.zeros(9),
            )
            writer.write(mag_conn, t_ns, STORE.serialize_cdr(mag, "sensor_msgs/msg/MagneticField"))
            writer.write(imu_conn, t_ns, STORE.serialize_cdr(imu, "sensor_msgs/msg/Imu"))


@pytest.fixture(scope="module")
def ck(datasets_dir):
    data = np.genfromtxt(datasets_dir / "ck_explorer_acc_mag_log.csv", delimiter=",", names=True)
    columns = [np.column_stack([data[f"{k}x"], data[f"{k}y"], data[f"{k}z"]]) for k in ("m", "a")]
    return datasets_dir / "ck_explorer_acc_mag_log.csv", columns[0], columns[1]


def fit(capsys, *args):
    assert main(["fit", *args, "--method", "ellipsoid"]) == 0
    return json.loads(capsys.readouterr().out)


@pytest.mark.integration  # seconds, not milliseconds: 24,000 messages written and read, two fits of 12,000 samples
def test_a_real_recording_as_rosbag2_fits_as_its_csv(ck, tmp_path, capsys):
    csv, mag_gauss, acc_g = ck
    write_bag(tmp_path / "ck", mag_gauss, acc_g)
    from_csv = fit(capsys, str(csv), "--unit", "gauss")
    from_bag = fit(capsys, str(tmp_path / "ck"))  # the bag reads in uT: 1 gauss = 100 uT
    np.testing.assert_allclose(from_bag["offset"], np.array(from_csv["offset"]) * 100, rtol=1e-9)
    np.testing.assert_allclose(from_bag["matrix"], np.array(from_csv["matrix"]) / 100, rtol=1e-9)
    assert from_bag["field_strength"] == pytest.approx(from_csv["field_strength"], rel=1e-12)
    for name in ("residual_rms", "coverage", "residual_rms_pct"):
        assert from_bag["quality"][name] == pytest.approx(from_csv["quality"][name], rel=1e-9), name
    bare = read_input(tmp_path / "ck" / "ck.mcap", InputOptions(topic="/ck/mag"))
    np.testing.assert_allclose(bare.mag, mag_gauss * 100, rtol=1e-12)


def test_a_db3_bag_reads_with_acceleration_in_magnets_frame(ck, tmp_path):
    _, mag_gauss, acc_g = ck
    write_bag(tmp_path / "small", mag_gauss[:50], acc_g[:50], StoragePlugin.SQLITE3)
    table = read_input(tmp_path / "small" / "small.db3")
    np.testing.assert_allclose(table.mag, mag_gauss[:50] * 100, rtol=1e-12)
    np.testing.assert_allclose(table.acc, acc_g[:50] * G, rtol=1e-12)
    assert "/ck/mag with /ck/imu" in table.note


def test_a_wrong_topic_is_one_clear_line(ck, tmp_path, capsys):
    _, mag_gauss, acc_g = ck
    write_bag(tmp_path / "b", mag_gauss[:5], acc_g[:5])
    with pytest.raises(ValueError, match="/ck/imu"):
        read_input(tmp_path / "b", InputOptions(topic="/ck/imu"))
    assert main(["fit", str(tmp_path / "b"), "--topic", "/nope", "--method", "ellipsoid"]) == 2
    assert "/nope" in capsys.readouterr().err


def test_edge_replay_reads_a_bag_at_its_recorded_pace(ck, tmp_path):
    from services.edge.sources import read_recording

    _, mag_gauss, acc_g = ck
    write_bag(tmp_path / "r", mag_gauss[:20], acc_g[:20])
    recording = read_recording(tmp_path / "r" / "r.mcap", "/ck/mag")
    np.testing.assert_allclose(np.diff(recording.t_s), 0.01, atol=1e-6)  # the stamps' 100 Hz
    np.testing.assert_allclose(recording.mag_ut, mag_gauss[:20] * 100, rtol=1e-12)


def test_record_refuses_messages_that_do_not_decode():
    from magnet import wire
    from services.commands.record import _rows

    for kind in (wire.Kind.RAW, wire.Kind.HEADING, wire.Kind.CALIBRATION, wire.Kind.ALERT):
        with pytest.raises(ValueError):
            _rows(kind, b"\x93garbage", "/magnet")
