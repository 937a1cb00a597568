"""The ROS 2 messages magnet speaks, as CDR bytes: built from arrays (one message per sample) and read back into
arrays with their checks. Definitions and serialisation are rosbags' (its Jazzy store; the types used here have the
same definitions and RIHS01 hashes in Kilted).

Units and frames are ROS 2's (``magnet.ros2.frames`` converts): field in tesla, body FLU, orientation body FLU ->
ENU. Covariances follow the messages' own rules: all zeros is "unknown"; for Imu, element 0 set to -1 means "this
quantity is not given" (and its values are zeros).
"""

from __future__ import annotations

import dataclasses
import functools
from collections.abc import Sequence
from typing import Any

import numpy as np
from rosbags.typesys import Stores, get_typestore

from magnet.ros2.cdr import stamped_doubles_cdr

__all__ = [
    "DIAGNOSTIC_ARRAY",
    "IMU",
    "MAGNETIC_FIELD",
    "STORE",
    "DeviceDiagnostic",
    "ImuSample",
    "MagSample",
    "decode_imu",
    "decode_magnetic_field",
    "diagnostic_array_cdr",
    "imu_cdr",
    "magnetic_field_cdr",
    "type_hash",
]

STORE = get_typestore(Stores.ROS2_JAZZY)
MAGNETIC_FIELD = "sensor_msgs/msg/MagneticField"
IMU = "sensor_msgs/msg/Imu"
DIAGNOSTIC_ARRAY = "diagnostic_msgs/msg/DiagnosticArray"
_T = STORE.types
_ZERO9 = np.zeros(9)
_NOT_GIVEN = np.array([-1.0, 0, 0, 0, 0, 0, 0, 0, 0])
_IDENTITY_XYZW = np.array([0.0, 0.0, 0.0, 1.0])
_ZERO3 = np.zeros(3)
MAX_FIELD_T = 1e-2  # 10 mT: no magnetometer in the Earth's field reads more
MAX_ACC_MS2 = 2000.0
MAX_GYR_RADS = 200.0


@functools.cache
def type_hash(ros_type: str) -> str:
    """The RIHS01 type hash of a message type (``RIHS01_`` and 64 hex digits), as rmw_zenoh puts in keys."""
    return str(STORE.hash_rihs01(ros_type))


def _header(t_ns: int, frame_id: str) -> Any:
    sec, nanosec = divmod(int(t_ns), 1_000_000_000)
    return _T["std_msgs/msg/Header"](_T["builtin_interfaces/msg/Time"](sec, nanosec), frame_id)


def magnetic_field_values(field_t: np.ndarray, variance_t2: float | np.ndarray) -> np.ndarray:
    """(S, 12) the doubles of MagneticField: field_t (S, 3) tesla, then the covariance with ``variance_t2`` (T^2,
    one for all or (S,)) on its diagonal (0: unknown, all zeros)."""
    field_t = np.asarray(field_t, dtype=float).reshape(-1, 3)
    variance = np.broadcast_to(np.asarray(variance_t2, dtype=float), (len(field_t),))
    cov = np.clip(variance, 0.0, None)[:, None] * np.eye(3).ravel()
    return np.concatenate([field_t, cov], axis=1)


def imu_values(
    quat_xyzw: np.ndarray | None,
    gyr_rads: np.ndarray | None,
    acc_ms2: np.ndarray | None,
    count: int,
    orientation_variance: np.ndarray | None = None,
) -> np.ndarray:
    """(S, 37) the doubles of Imu: orientation, its covariance, angular velocity, its covariance, linear
    acceleration, its covariance. A row with a NaN (or None for all) is not given: -1 in element 0 of its
    covariance, zeros (the identity for the orientation) as values; a given one has an unknown (zero) covariance,
    except the orientation's where ``orientation_variance`` (S, 3) rad^2 about the parent frame's x, y and z (ENU:
    the two tilts and the yaw) has a finite row: those on its diagonal (elements 0, 4, 8)."""
    parts = []
    for values, width, missing in ((quat_xyzw, 4, _IDENTITY_XYZW), (gyr_rads, 3, _ZERO3), (acc_ms2, 3, _ZERO3)):
        rows = np.full((count, width), np.nan) if values is None else np.asarray(values, dtype=float)
        given = np.isfinite(rows).all(axis=1)[:, None]
        parts += [np.where(given, rows, missing), np.where(given, _ZERO9, _NOT_GIVEN)]
    if orientation_variance is not None:
        variance = np.asarray(orientation_variance, dtype=float).reshape(count, 3)
        known = np.isfinite(variance).all(axis=1)[:, None] & (parts[1][:, :1] != -1.0)
        diagonal = np.zeros((count, 9))
        diagonal[:, [0, 4, 8]] = np.clip(np.nan_to_num(variance), 0.0, None)
        parts[1] = np.where(known, diagonal, parts[1])
    return np.concatenate(parts, axis=1)


def magnetic_field_cdr(t_ns: np.ndarray, frame_id: str, field_t: np.ndarray, variance_t2: float) -> list[bytes]:
    """One ``sensor_msgs/msg/MagneticField`` per sample: t_ns (S,) ns since the epoch, field_t (S, 3) tesla;
    ``variance_t2`` (T^2) on the covariance's diagonal, 0 for unknown (all zeros)."""
    return stamped_doubles_cdr(t_ns, frame_id, magnetic_field_values(field_t, variance_t2))


def imu_cdr(
    t_ns: np.ndarray,
    frame_id: str,
    quat_xyzw: np.ndarray,
    gyr_rads: np.ndarray | None,
    acc_ms2: np.ndarray | None,
) -> list[bytes]:
    """One ``sensor_msgs/msg/Imu`` per sample: t_ns (S,), quat_xyzw (S, 4) body FLU -> ENU, gyr_rads and acc_ms2
    (S, 3) FLU or None (see ``imu_values``)."""
    return stamped_doubles_cdr(t_ns, frame_id, imu_values(quat_xyzw, gyr_rads, acc_ms2, len(t_ns)))


@dataclasses.dataclass(frozen=True)
class DeviceDiagnostic:
    """One device's state for ``/diagnostics``: level 0 OK, 1 WARN, 2 ERROR, 3 STALE; a one-line message; values
    as (key, text) pairs."""

    device: str
    level: int
    message: str
    values: tuple[tuple[str, str], ...] = ()


def diagnostic_array_cdr(t_ns: int, devices: Sequence[DeviceDiagnostic], name_prefix: str = "magnet") -> bytes:
    """One ``diagnostic_msgs/msg/DiagnosticArray`` with a status per device (name ``<name_prefix>: <device>``,
    hardware_id the device id)."""
    status, pair = _T["diagnostic_msgs/msg/DiagnosticStatus"], _T["diagnostic_msgs/msg/KeyValue"]
    statuses = [
        status(d.level, f"{name_prefix}: {d.device}", d.message, d.device, [pair(k, v) for k, v in d.values])
        for d in devices
    ]
    return bytes(STORE.serialize_cdr(_T[DIAGNOSTIC_ARRAY](_header(t_ns, ""), statuses), DIAGNOSTIC_ARRAY))


@dataclasses.dataclass(frozen=True)
class MagSample:
    """A MagneticField read back: t_ns, frame_id, field_t (3,) tesla FLU."""

    t_ns: int
    frame_id: str
    field_t: np.ndarray


@dataclasses.dataclass(frozen=True)
class ImuSample:
    """An Imu read back: t_ns, frame_id, acc_ms2 and gyr_rads (3,) FLU or None where the message says not given."""

    t_ns: int
    frame_id: str
    acc_ms2: np.ndarray | None
    gyr_rads: np.ndarray | None


def _deserialize(data: bytes, ros_type: str) -> Any:
    """rosbags' message of ``data``; ValueError for bytes that are not one whole message of ``ros_type``."""
    if len(data) < 8 or data[:2] not in (b"\x00\x01", b"\x00\x00"):
        raise ValueError(f"not CDR ({len(data)} bytes, encapsulation {data[:2].hex()!r}); {ros_type} expected")
    try:  # rosbags refuses a message cut short or followed by more than 3 bytes of end padding
        return STORE.deserialize_cdr(data, ros_type)
    except Exception as exc:  # rosbags raises whatever its parser meets: every one is a malformed message here
        raise ValueError(f"malformed {ros_type} CDR ({len(data)} bytes): {type(exc).__name__}") from exc


def _stamp_ns(msg: Any) -> int:
    stamp = msg.header.stamp
    if stamp.sec < 0 or not 0 <= stamp.nanosec < 1_000_000_000:
        raise ValueError(f"header stamp {stamp.sec} s {stamp.nanosec} ns is not a time")
    return int(stamp.sec) * 1_000_000_000 + int(stamp.nanosec)


def _checked(v: Any, limit: float, what: str) -> np.ndarray:
    out = np.array([v.x, v.y, v.z], dtype=float)
    if not np.isfinite(out).all() or np.abs(out).max() > limit:
        raise ValueError(f"{what} {out.tolist()} is not finite or beyond {limit:g}")
    return out


def decode_magnetic_field(data: bytes) -> MagSample:
    """A ``sensor_msgs/msg/MagneticField`` from CDR bytes; ValueError for anything malformed or absurd."""
    msg = _deserialize(data, MAGNETIC_FIELD)
    return MagSample(_stamp_ns(msg), msg.header.frame_id, _checked(msg.magnetic_field, MAX_FIELD_T, "field (T)"))


def decode_imu(data: bytes) -> ImuSample:
    """A ``sensor_msgs/msg/Imu`` from CDR bytes; acc/gyr None where element 0 of their covariance is -1."""
    msg = _deserialize(data, IMU)
    acc = None if msg.linear_acceleration_covariance[0] == -1 else msg.linear_acceleration
    gyr = None if msg.angular_velocity_covariance[0] == -1 else msg.angular_velocity
    return ImuSample(
        _stamp_ns(msg),
        msg.header.frame_id,
        None if acc is None else _checked(acc, MAX_ACC_MS2, "linear acceleration (m/s^2)"),
        None if gyr is None else _checked(gyr, MAX_GYR_RADS, "angular velocity (rad/s)"),
    )
