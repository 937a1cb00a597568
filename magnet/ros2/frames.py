"""magnet's frames to ROS 2's (REP-103), in one place: the only conversion between them.

magnet: body x forward, y right, z down (FRD); earth north, east, down (NED); field in uT; heading clockwise from
north. ROS 2 (REP-103): body x forward, y left, z up (FLU); earth east, north, up (ENU); field in tesla; yaw
counter-clockwise from east. A body vector (x, y, z) FRD is (x, -y, -z) FLU (a half turn about x). An earth vector
(n, e, d) NED is (e, n, -d) ENU. An attitude q (body FRD -> NED) becomes q_enu_ned * q * q_frd_flu (body FLU -> ENU):
a level device pointing north has ROS yaw +90 deg.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from magnet.attitude import quaternion_multiply

__all__ = ["TESLA_PER_UT", "RosFrames", "from_ros", "ros_yaw_deg", "to_ros"]

TESLA_PER_UT = 1e-6
_FLIP_YZ = np.array([1.0, -1.0, -1.0])  # FRD <-> FLU, its own inverse
_HALF = np.sqrt(0.5)
#: the rotation taking NED axes to ENU axes (half a turn about the north-east diagonal), w x y z
_Q_ENU_NED = np.array([0.0, _HALF, _HALF, 0.0])
#: the rotation taking FLU body axes to FRD body axes (half a turn about x), w x y z
_Q_FRD_FLU = np.array([0.0, 1.0, 0.0, 0.0])


@dataclasses.dataclass(frozen=True, eq=False)
class RosFrames:
    """Samples in ROS 2's frames and units. field_t (S, 3) tesla FLU; acc_ms2 (S, 3) m/s^2 FLU specific force (a
    level device at rest reads +9.81 on z); gyr_rads (S, 3) rad/s FLU or None; quat_xyzw (S, 4) body FLU -> ENU in
    ROS's field order x, y, z, w (NaN rows where unknown)."""

    field_t: np.ndarray
    acc_ms2: np.ndarray
    gyr_rads: np.ndarray | None
    quat_xyzw: np.ndarray


def _orientation(quat_wxyz_ned_frd: np.ndarray) -> np.ndarray:
    """(S, 4) body FRD -> NED, w x y z, to (S, 4) body FLU -> ENU, x y z w with w >= 0."""
    q = quaternion_multiply(quaternion_multiply(_Q_ENU_NED, np.asarray(quat_wxyz_ned_frd, dtype=float)), _Q_FRD_FLU)
    q = q * np.where(q[..., :1] < 0, -1.0, 1.0)
    return np.concatenate([q[..., 1:], q[..., :1]], axis=-1)


def to_ros(field_ut: np.ndarray, acc_ms2: np.ndarray, gyr_rads: np.ndarray | None, quat_wxyz: np.ndarray) -> RosFrames:
    """magnet's samples in ROS 2's frames: field_ut (S, 3) uT FRD, acc_ms2 (S, 3) m/s^2 FRD, gyr_rads (S, 3) rad/s
    FRD or None, quat_wxyz (S, 4) body FRD -> NED (true north). The one conversion at the ROS 2 boundary."""
    return RosFrames(
        np.asarray(field_ut, dtype=float) * (_FLIP_YZ * TESLA_PER_UT),
        np.asarray(acc_ms2, dtype=float) * _FLIP_YZ,
        None if gyr_rads is None else np.asarray(gyr_rads, dtype=float) * _FLIP_YZ,
        _orientation(quat_wxyz),
    )


def from_ros(
    field_t: np.ndarray, acc_ms2: np.ndarray, gyr_rads: np.ndarray | None
) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """The inverse for what a ROS 2 source sends: field (S, 3) tesla FLU, acc (S, 3) m/s^2 FLU, gyr (S, 3) rad/s FLU
    or None to (field_ut, acc_ms2, gyr_rads) in magnet's FRD body frame."""
    return (
        np.asarray(field_t, dtype=float) * (_FLIP_YZ / TESLA_PER_UT),
        np.asarray(acc_ms2, dtype=float) * _FLIP_YZ,
        None if gyr_rads is None else np.asarray(gyr_rads, dtype=float) * _FLIP_YZ,
    )


def ros_yaw_deg(heading_deg: np.ndarray) -> np.ndarray:
    """ROS yaw (counter-clockwise from east, degrees in (-180, 180]) of a heading (clockwise from north)."""
    yaw = 90.0 - np.asarray(heading_deg, dtype=float)
    return np.asarray(180.0 - np.mod(180.0 - yaw, 360.0))
