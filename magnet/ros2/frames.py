"""magnet's samples in ROS 2's frames and units (REP-103), and back: the only conversion at the ROS 2 boundary.

ROS 2's frames are body FLU and earth ENU, its field in tesla, its yaw counter-clockwise from east; the frame maps
themselves (FRD <-> FLU, NED <-> ENU, attitudes) are ``magnet.frames``' (docs/frames.md). A level device pointing
north has ROS yaw +90 deg.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from magnet.frames import frd_flu, ned_enu_attitude

__all__ = ["TESLA_PER_UT", "RosFrames", "from_ros", "ros_yaw_deg", "to_ros"]

TESLA_PER_UT = 1e-6


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
    q = ned_enu_attitude(quat_wxyz_ned_frd)
    return np.concatenate([q[..., 1:], q[..., :1]], axis=-1)


def to_ros(field_ut: np.ndarray, acc_ms2: np.ndarray, gyr_rads: np.ndarray | None, quat_wxyz: np.ndarray) -> RosFrames:
    """magnet's samples in ROS 2's frames: field_ut (S, 3) uT FRD, acc_ms2 (S, 3) m/s^2 FRD, gyr_rads (S, 3) rad/s
    FRD or None, quat_wxyz (S, 4) body FRD -> NED (true north). The one conversion at the ROS 2 boundary."""
    return RosFrames(
        frd_flu(field_ut) * TESLA_PER_UT,
        frd_flu(acc_ms2),
        None if gyr_rads is None else frd_flu(gyr_rads),
        _orientation(quat_wxyz),
    )


def from_ros(
    field_t: np.ndarray, acc_ms2: np.ndarray, gyr_rads: np.ndarray | None
) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """The inverse for what a ROS 2 source sends: field (S, 3) tesla FLU, acc (S, 3) m/s^2 FLU, gyr (S, 3) rad/s FLU
    or None to (field_ut, acc_ms2, gyr_rads) in magnet's FRD body frame."""
    return (
        frd_flu(field_t) * (1 / TESLA_PER_UT),
        frd_flu(acc_ms2),
        None if gyr_rads is None else frd_flu(gyr_rads),
    )


def ros_yaw_deg(heading_deg: np.ndarray) -> np.ndarray:
    """ROS yaw (counter-clockwise from east, degrees in (-180, 180]) of a heading (clockwise from north)."""
    yaw = 90.0 - np.asarray(heading_deg, dtype=float)
    return np.asarray(180.0 - np.mod(180.0 - yaw, 360.0))
