"""magnet's messages as ROS 2 messages for a recording (pure): each raw batch, heading batch, calibration and alert
becomes (topic, type, log time ns, CDR bytes) rows that a rosbag2 writer stores. Topics, under a namespace (default
``/magnet``) and the device's ROS name:

- ``<NS>/<device>/raw/mag`` MagneticField: the raw field (uncalibrated), tesla FLU; ``<NS>/<device>/raw/imu`` Imu:
  accelerometer and gyroscope as sent (no orientation);
- ``<NS>/<device>/mag`` MagneticField and ``<NS>/<device>/imu`` Imu: the compass's calibrated field and attitude, as
  ``magnet compass --ros2`` publishes them;
- ``<NS>/<device>/calibration`` and ``<NS>/<device>/alert`` std_msgs/msg/String: the wire record as JSON.
"""

from __future__ import annotations

import json
from typing import Any

import numpy as np

from magnet import wire
from magnet.ros2 import compass as ros_compass
from magnet.ros2 import messages
from magnet.ros2.frames import to_ros
from magnet.ros2.names import DEFAULT_NAMESPACE, ros_name_of_device, topic_name

__all__ = ["STRING", "Row", "alert_rows", "calibration_rows", "heading_rows", "raw_rows"]

STRING = "std_msgs/msg/String"
Row = tuple[str, str, int, bytes]  # topic, type, log time ns, CDR


def raw_rows(batch: wire.RawBatch, namespace: str = DEFAULT_NAMESPACE) -> list[Row]:
    """A MagneticField (raw field) and, when the batch has an accelerometer, an Imu per sample."""
    n = len(batch)
    nan = np.full((n, 3), np.nan)
    acc = batch.acc_ms2 if batch.acc_ms2 is not None else nan
    gyr = batch.gyr_rads if batch.gyr_rads is not None else nan
    ros = to_ros(batch.mag_ut, acc, gyr, np.full((n, 4), np.nan))
    frame, t_ns = ros_name_of_device(batch.device), np.asarray(batch.t_ns, dtype=np.int64)
    mag_topic, imu_topic = (topic_name(namespace, batch.device, leaf) for leaf in ("raw/mag", "raw/imu"))
    rows = [
        (mag_topic, messages.MAGNETIC_FIELD, t, cdr)
        for t, cdr in zip(t_ns.tolist(), messages.magnetic_field_cdr(t_ns, frame, ros.field_t, 0.0))
    ]
    if batch.acc_ms2 is not None:
        imus = messages.imu_cdr(t_ns, frame, ros.quat_xyzw, ros.gyr_rads, ros.acc_ms2)
        rows += [(imu_topic, messages.IMU, t, cdr) for t, cdr in zip(t_ns.tolist(), imus)]
    return rows


def heading_rows(batch: wire.HeadingBatch, namespace: str = DEFAULT_NAMESPACE) -> list[Row]:
    """The compass's calibrated field and attitude per sample, as ``magnet compass --ros2`` publishes them."""
    n = len(batch)
    quat = ros_compass.attitude_wxyz(batch.quat_wxyz, batch.true_heading_deg, batch.pitch_deg, batch.roll_deg)
    nan = np.full((n, 3), np.nan)
    t_ns = np.asarray(batch.t_ns, dtype=np.int64)
    mag, imu = ros_compass.sample_messages(batch.device, t_ns, batch.field_ut, nan, nan, quat, 0.0)
    mag_topic, imu_topic = (topic_name(namespace, batch.device, leaf) for leaf in ("mag", "imu"))
    times = t_ns.tolist()
    return [(mag_topic, messages.MAGNETIC_FIELD, t, m) for t, m in zip(times, mag)] + [
        (imu_topic, messages.IMU, t, u) for t, u in zip(times, imu)
    ]


def _string(text: str) -> bytes:
    return bytes(messages.STORE.serialize_cdr(messages.STORE.types[STRING](text), STRING))


def calibration_rows(record: dict[str, Any], t_ns: int, namespace: str = DEFAULT_NAMESPACE) -> list[Row]:
    """The calibration record (the wire map, ``magnet.wire.calibration_record``) as JSON text."""
    topic = topic_name(namespace, str(record["device"]), "calibration")
    return [(topic, STRING, t_ns, _string(json.dumps(record, sort_keys=True, default=_plain)))]


def alert_rows(message: dict[str, Any], t_ns: int, namespace: str = DEFAULT_NAMESPACE) -> list[Row]:
    """An alert message (the wire map) as JSON text."""
    topic = topic_name(namespace, str(message["device"]), "alert")
    return [(topic, STRING, t_ns, _string(json.dumps(message, sort_keys=True, default=_plain)))]


def _plain(value: Any) -> Any:
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, bytes):
        return value.hex()
    return str(value)
