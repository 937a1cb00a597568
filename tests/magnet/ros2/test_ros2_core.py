"""The pure ROS 2 side (``magnet.ros2``): type hashes equal the third-party client's and published ones, keys and
liveliness tokens equal the ones zenoh-ros2-sdk builds, REP-103 frames, the reversible device-name rule, CDR
messages read back by rosbags, malformed or mistyped CDR refused."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from ros2_sdk_client import dependencies, msg_text
from rosbags.typesys import Stores, get_typestore

from magnet.frames import euler_to_quaternion
from magnet.ros2 import compass as rc
from magnet.ros2 import frames, messages, names
from magnet.ros2.pairing import SamplePairer

TYPES = (messages.MAGNETIC_FIELD, messages.IMU, messages.DIAGNOSTIC_ARRAY)
#: published by projects that took them from a ROS 2 Jazzy build (found with the search tool)
PUBLISHED = {
    messages.IMU: "RIHS01_7d9a00ff131080897a5ec7e26e315954b8eae3353c3f995c55faf71574000b5b",
    messages.DIAGNOSTIC_ARRAY: "RIHS01_5a8a36efb05fb25070fa0fb3810290c0e6cd4862b54a8fb975a1ee8dc55a333e",
}


@pytest.mark.parametrize("ros_type", TYPES)
def test_type_hashes_equal_the_third_party_clients_and_kilted_and_published(ros_type):
    from zenoh_ros2_sdk.utils import get_type_hash

    ours = messages.type_hash(ros_type)
    assert ours == get_type_hash(ros_type, msg_definition=msg_text(ros_type), dependencies=dependencies(ros_type))
    assert ours == get_typestore(Stores.ROS2_KILTED).hash_rihs01(ros_type)
    assert ours == PUBLISHED.get(ros_type, ours)


def test_keys_and_tokens_are_the_ones_the_third_party_client_builds():
    from zenoh_ros2_sdk.entity import EndpointEntity, EntityKind, NodeEntity
    from zenoh_ros2_sdk.keyexpr import endpoint_liveliness_keyexpr, node_liveliness_keyexpr, topic_keyexpr
    from zenoh_ros2_sdk.qos import DEFAULT_QOS_PROFILE

    zid, topic, hash_ = "1f2e3d", "/magnet/ximu_2d1/mag", messages.type_hash(messages.MAGNETIC_FIELD)
    node = NodeEntity(domain_id=3, session_id=zid, node_id=0, node_name="compass", namespace="/magnet")
    ep = EndpointEntity(
        node,
        4,
        EntityKind.PUBLISHER,
        topic,
        "sensor_msgs::msg::dds_::MagneticField_",
        hash_,
        DEFAULT_QOS_PROFILE.encode(),
    )
    assert names.topic_key(3, topic, messages.MAGNETIC_FIELD, hash_) == topic_keyexpr(
        3, topic, "sensor_msgs::msg::dds_::MagneticField_", hash_
    )
    assert names.node_token(3, zid, 0, "/magnet", "compass") == node_liveliness_keyexpr(node)
    ours = names.endpoint_token(
        3, zid, 0, "/magnet", "compass", names.Endpoint("MP", topic, messages.MAGNETIC_FIELD, hash_, 4)
    )
    assert ours == endpoint_liveliness_keyexpr(ep)


def test_the_attachment_reads_back_with_the_third_party_client():
    from zenoh_ros2_sdk.attachment import Attachment

    gid = names.gid_of("@ros2_lv/0/x")
    back = Attachment.from_bytes(names.Attachment(7, 1_700_000_000_000_000_001, gid).to_bytes())
    assert (back.sequence_id, back.timestamp_ns, back.gid) == (7, 1_700_000_000_000_000_001, gid)
    with pytest.raises(ValueError, match="GID"):
        names.Attachment.from_bytes(names.Attachment(7, 1, gid).to_bytes()[:-1])


@settings(max_examples=40)
@given(st.text(min_size=1, max_size=40).filter(lambda s: s.isprintable() and s.strip() == s))
def test_every_device_id_maps_to_a_ros_name_and_back(device):
    name = names.ros_name_of_device(device)
    assert names.device_from_ros_name(name) == device
    assert name[0].isalpha() and "__" not in name and not name.endswith("_")
    assert all(c.isascii() and (c.isalnum() or c == "_") for c in name)


def test_clean_ids_stay_as_they_are_and_others_are_escaped():
    assert names.ros_name_of_device("compass_1") == "compass_1"
    assert names.ros_name_of_device("imu-1") == "ximu_2d1"
    assert names.ros_name_of_device("xsens") == "xxsens"
    assert names.topic_name("/magnet", "imu-1", "mag") == "/magnet/ximu_2d1/mag"
    with pytest.raises(ValueError):
        names.validate_namespace("magnet/")


def test_rep103_a_level_device_facing_north_has_ros_yaw_90_and_gravity_up():
    ros = frames.to_ros(np.array([[20.0, 0.0, 45.0]]), np.array([[0, 0, -9.81]]), None, np.array([[1.0, 0, 0, 0]]))
    np.testing.assert_allclose(ros.quat_xyzw, [[0, 0, np.sqrt(0.5), np.sqrt(0.5)]], atol=1e-12)
    np.testing.assert_allclose(ros.field_t, [[20e-6, 0, -45e-6]])  # north (forward) and down (-z up)
    np.testing.assert_allclose(ros.acc_ms2, [[0, 0, 9.81]])
    facing_east = frames.to_ros(np.zeros((1, 3)), np.zeros((1, 3)), None, euler_to_quaternion([90.0], [0.0], [0.0]))
    np.testing.assert_allclose(facing_east.quat_xyzw, [[0, 0, 0, 1]], atol=1e-12)  # ROS yaw 0: x east
    np.testing.assert_allclose(frames.ros_yaw_deg(np.array([0.0, 90.0, 270.0])), [90.0, 0.0, 180.0])
    back = frames.from_ros(ros.field_t, ros.acc_ms2, ros.acc_ms2)
    np.testing.assert_allclose(back[0], [[20.0, 0.0, 45.0]])


def test_messages_read_back_with_rosbags_and_carry_the_conventions():
    store = get_typestore(Stores.ROS2_JAZZY)
    t_ns = np.array([1_700_000_000_123_456_789, 1_700_000_000_133_456_789])
    mag, imu = rc.sample_messages(
        "imu-1",
        t_ns,
        np.array([[20.0, 1.0, 45.0]] * 2),
        np.array([[0, 0, -9.81], [np.nan] * 3]),
        np.array([[np.nan] * 3] * 2),
        np.array([[1.0, 0, 0, 0], [np.nan] * 4]),
        rc.field_variance_t2(0.5),
    )
    m = store.deserialize_cdr(mag[0], messages.MAGNETIC_FIELD)
    assert (m.header.stamp.sec, m.header.stamp.nanosec, m.header.frame_id) == (1_700_000_000, 123_456_789, "ximu_2d1")
    np.testing.assert_allclose(m.magnetic_field_covariance, np.eye(3).ravel() * 0.25e-12)
    first, second = (store.deserialize_cdr(b, messages.IMU) for b in imu)
    assert first.angular_velocity_covariance[0] == -1 and first.linear_acceleration_covariance[0] == 0
    assert second.orientation_covariance[0] == -1 and second.linear_acceleration_covariance[0] == -1
    decoded = messages.decode_imu(imu[0])
    assert decoded.gyr_rads is None and decoded.acc_ms2 is not None


def test_malformed_or_mistyped_cdr_is_refused_with_a_reason():
    mag = messages.magnetic_field_cdr(np.array([1]), "d", np.array([[1e-5, 0, 0]]), 0.0)[0]
    imu = messages.imu_cdr(np.array([1]), "d", np.array([[0, 0, 0, 1.0]]), None, None)[0]
    for bad in (b"", b"\x00\x01\x00\x00", mag[:-3], b"\xff" * 64, imu):
        with pytest.raises(ValueError):
            messages.decode_magnetic_field(bad)
    with pytest.raises(ValueError):
        messages.decode_imu(mag)
    absurd = messages.magnetic_field_cdr(np.array([1]), "d", np.array([[np.nan, 0, 0]]), 0.0)[0]
    with pytest.raises(ValueError, match="not finite"):
        messages.decode_magnetic_field(absurd)


def test_diagnostics_levels_follow_calibration_alerts_and_disturbance():
    assert rc.device_diagnostic(rc.DeviceState("d", "c1", "ellipsoid", 0.3)).level == 0
    assert rc.device_diagnostic(rc.DeviceState("d")).level == 1
    assert rc.device_diagnostic(rc.DeviceState("d", "c1", disturbed_share=0.9)).level == 1
    status = rc.device_diagnostic(rc.DeviceState("d", "c1", alerts=("dip",)))
    assert status.level == 2 and "dip" in status.message
    array = get_typestore(Stores.ROS2_JAZZY).deserialize_cdr(
        messages.diagnostic_array_cdr(5, [status]), messages.DIAGNOSTIC_ARRAY
    )
    assert array.status[0].hardware_id == "d" and {v.key: v.value for v in array.status[0].values}["alerts"] == "dip"


def _mag(t_ns: int) -> messages.MagSample:
    return messages.MagSample(t_ns, "d", np.array([20e-6, 1e-6, -45e-6]))


def _imu(t_ns: int, gyro: bool = True) -> messages.ImuSample:
    return messages.ImuSample(t_ns, "d", np.array([0.0, 0.0, 9.81]), np.array([0.1, 0.0, 0.0]) if gyro else None)


def test_field_and_imu_are_joined_by_time_into_magnets_frame():
    pairer = SamplePairer(with_imu=True, batch=3)
    for k in range(3):
        pairer.add_mag(_mag(1_000 + k * 10_000_000), now_s=0.0)
    assert pairer.batches(now_s=0.01) == []  # waiting for the Imu of their time
    for k in range(3):
        pairer.add_imu(_imu(1_000 + k * 10_000_000 + 2_000_000))
    (joined,) = pairer.batches(now_s=0.02)
    np.testing.assert_allclose(joined.mag_ut, [[20.0, -1.0, 45.0]] * 3)  # FLU tesla -> FRD uT
    np.testing.assert_allclose(joined.acc_ms2, [[0, 0, -9.81]] * 3)
    np.testing.assert_allclose(joined.gyr_rads, [[0.1, 0, 0]] * 3)


def test_without_an_imu_in_time_the_field_goes_alone_after_the_wait():
    pairer = SamplePairer(with_imu=True, batch=10, wait_s=0.2, flush_s=0.25)
    pairer.add_mag(_mag(5), now_s=0.0)
    pairer.add_imu(_imu(5 + 10**9))  # a second later: too far to pair
    (joined,) = pairer.batches(now_s=0.3)
    assert joined.acc_ms2 is None and joined.gyr_rads is None and len(joined.t_ns) == 1


def test_foxglove_views_of_a_heading_use_the_same_frames():
    from magnet import wire
    from services.dashboard.foxglove import heading_views

    batch = wire.HeadingBatch(
        "imu-1",
        0,
        np.array([5, 1_000_000_007]),
        np.array([10.0, 0.0]),
        np.array([12.0, 0.0]),
        np.zeros(2),
        np.zeros(2),
        np.array([[20.0, 1.0, 45.0]] * 2),
        0.0,
        "c1",
        np.array([0, 1]),
    )
    heading, field, rotation = heading_views(batch)
    assert heading["t_ns"] == 1_000_000_007 and heading["ros_yaw_deg"] == pytest.approx(90.0)
    assert field["y_ut"] == pytest.approx(-1.0) and field["z_ut"] == pytest.approx(-45.0)
    np.testing.assert_allclose(rotation, [0, 0, np.sqrt(0.5), np.sqrt(0.5)], atol=1e-12)  # level, facing north


@pytest.mark.parametrize("frame_id", ["", "d", "ab", "abc", "ximu_2d1", "a_somewhat_longer_frame"])
def test_the_batch_cdr_is_byte_for_byte_rosbags_serialisation(frame_id):
    store = get_typestore(Stores.ROS2_JAZZY)
    t = store.types
    rng = np.random.default_rng(3)
    t_ns = np.array([1_700_000_000_123_456_789, 5, 2_000_000_000_999_999_999])
    field, quat, vec = rng.normal(size=(3, 3)) * 1e-5, rng.normal(size=(3, 4)), rng.normal(size=(3, 3))
    quat[1] = np.nan  # no orientation in the second sample
    mags = messages.magnetic_field_cdr(t_ns, frame_id, field, 4e-14)
    imus = messages.imu_cdr(t_ns, frame_id, quat, None, vec)
    unknown, none = np.zeros(9), np.array([-1.0] + [0.0] * 8)
    for k, stamp in enumerate(t_ns.tolist()):
        header = t["std_msgs/msg/Header"](t["builtin_interfaces/msg/Time"](*divmod(stamp, 10**9)), frame_id)
        vector = t["geometry_msgs/msg/Vector3"]
        mag = t["sensor_msgs/msg/MagneticField"](header, vector(*field[k]), np.eye(3).ravel() * 4e-14)
        assert mags[k] == bytes(store.serialize_cdr(mag, messages.MAGNETIC_FIELD))
        has_q = k != 1
        q = t["geometry_msgs/msg/Quaternion"](*(quat[k] if has_q else (0.0, 0.0, 0.0, 1.0)))
        imu = t["sensor_msgs/msg/Imu"](
            header, q, unknown if has_q else none, vector(0.0, 0.0, 0.0), none, vector(*vec[k]), unknown
        )
        assert imus[k] == bytes(store.serialize_cdr(imu, messages.IMU))
