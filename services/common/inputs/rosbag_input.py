"""ROS 2 recordings (rosbag2: a bag directory, or its ``.mcap`` or ``.db3`` file) as offline input, read with
rosbags: the ``sensor_msgs/msg/MagneticField`` samples of one topic (``--topic``, or the only such topic), joined with
the ``sensor_msgs/msg/Imu`` samples of the same stamp (the sibling ``.../imu`` topic, or the only Imu topic) and
converted to magnet's frame (``magnet.ros2.frames.from_ros``): mx,my,mz in uT (so ``--unit ut``), ax,ay,az m/s^2,
gx,gy,gz rad/s, t_s from the header stamps. Messages that do not decode are skipped and counted in the note."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
from rosbags.rosbag2 import Reader

from magnet.ros2 import messages
from magnet.ros2.frames import from_ros
from services.common.inputs.csvio import SampleTable

PAIR_TOLERANCE_NS = 20_000_000


def _topics(reader: Any, ros_type: str) -> list[str]:
    return sorted({c.topic for c in reader.connections if c.msgtype == ros_type})


def _mag_topic(path: Path, reader: Any, asked: str | None) -> str:
    mags = _topics(reader, messages.MAGNETIC_FIELD)
    if asked is not None:
        if asked not in mags:
            raise ValueError(
                f"{path}: no {messages.MAGNETIC_FIELD} topic {asked!r}; it has {', '.join(mags) or 'none'}"
            )
        return asked
    if len(mags) != 1:
        listed = ", ".join(mags) or "none"
        raise ValueError(f"{path}: pick the MagneticField topic with --topic (the recording has: {listed})")
    return mags[0]


def _imu_topic(reader: Any, mag_topic: str) -> str | None:
    imus = _topics(reader, messages.IMU)
    sibling = mag_topic.rsplit("/", 1)[0] + "/imu"
    if sibling in imus:
        return sibling
    return imus[0] if len(imus) == 1 else None


def _read(reader: Any, topic: str, decode: Any) -> tuple[list[Any], int]:
    conns = [c for c in reader.connections if c.topic == topic]
    out, bad = [], 0
    for _, _, data in reader.messages(connections=conns):
        try:
            out.append(decode(bytes(data)))
        except ValueError:
            bad += 1
    return out, bad


def _join(mag_t: np.ndarray, imus: list[messages.ImuSample]) -> tuple[np.ndarray | None, np.ndarray | None]:
    """Per field sample, the acceleration and rates (FLU) of the Imu sample nearest in time (20 ms at most); None
    when any field sample has none."""
    usable = [i for i in imus if i.acc_ms2 is not None]
    if not usable or not len(mag_t):
        return None, None
    usable.sort(key=lambda i: i.t_ns)
    imu_t = np.array([i.t_ns for i in usable], dtype=np.int64)
    right = np.clip(np.searchsorted(imu_t, mag_t), 1, len(imu_t) - 1) if len(imu_t) > 1 else np.zeros_like(mag_t)
    left = np.maximum(right - 1, 0)
    nearest = np.where(np.abs(imu_t[left] - mag_t) <= np.abs(imu_t[right] - mag_t), left, right)
    if (np.abs(imu_t[nearest] - mag_t) > PAIR_TOLERANCE_NS).any():
        return None, None
    acc = np.array([usable[k].acc_ms2 for k in nearest])
    gyros = [usable[k].gyr_rads for k in nearest]
    gyr = None if any(g is None for g in gyros) else np.array(gyros)
    return acc, gyr


def read_rosbag(path: Path, topic: str | None) -> SampleTable:
    """The samples of a rosbag2 recording; ValueError naming the file and what to do."""
    try:
        reader = Reader(path)
        reader.open()
    except Exception as exc:  # rosbags raises its own errors for files it cannot read
        raise ValueError(f"{path}: not a rosbag2 recording rosbags can read ({exc})") from None
    try:
        mag_topic = _mag_topic(path, reader, topic)
        mags, bad_mag = _read(reader, mag_topic, messages.decode_magnetic_field)
        imu_topic = _imu_topic(reader, mag_topic)
        imus, bad_imu = _read(reader, imu_topic, messages.decode_imu) if imu_topic else ([], 0)
    finally:
        reader.close()
    if not mags:
        raise ValueError(f"{path}: topic {mag_topic} holds no MagneticField message that decodes")
    t_ns = np.array([m.t_ns for m in mags], dtype=np.int64)
    acc, gyr = _join(t_ns, imus)
    field = np.array([m.field_t for m in mags])
    mag_ut, acc_frd, gyr_frd = from_ros(field, acc if acc is not None else np.zeros_like(field), gyr)
    columns: dict[str, list[str] | np.ndarray] = {"t_s": t_ns / 1e9}
    for names, values in ((("mx", "my", "mz"), mag_ut), (("ax", "ay", "az"), acc_frd), (("gx", "gy", "gz"), gyr_frd)):
        if values is not None and (names[0] == "mx" or acc is not None):
            columns.update({name: values[:, k] for k, name in enumerate(names)})
    note = f"{len(mags)} samples of {_source_words(mag_topic, imu_topic, acc)} (uT, converted from ROS 2's FLU tesla)"
    if bad_mag or bad_imu:
        note += f"; skipped {bad_mag} MagneticField and {bad_imu} Imu messages that do not decode"
    return SampleTable(str(path), mag_ut, acc_frd if acc is not None else None, columns, note=note)


def _source_words(mag_topic: str, imu_topic: str | None, acc: np.ndarray | None) -> str:
    """Where the samples came from, in words."""
    if imu_topic is None:
        return f"{mag_topic} (no Imu topic)"
    return f"{mag_topic} with {imu_topic}" + ("" if acc is not None else " (not paired in time: no acceleration)")
