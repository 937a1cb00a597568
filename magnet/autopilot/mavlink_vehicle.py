"""What ``magnet.autopilot.mavlink_stream`` keeps per MAVLink vehicle (``Vehicle``, by system id) and per device
(``Pending``, a vehicle's compass instance): plain state, no behaviour."""

from __future__ import annotations

import dataclasses

import numpy as np

from magnet.autopilot.gyro_check import GyroCheck
from magnet.earth.location import Location


@dataclasses.dataclass
class Vehicle:
    """What is known of one vehicle (by MAVLink system id): the clock's offset, the last message (wall ns), its
    place, velocity, current and throttle with the wall ns each came, whether it is armed."""

    offset_ns: int | None = None
    last_boot_ns: int = 0
    last_seen_ns: int = 0
    location: Location | None = None
    velocity: tuple[np.ndarray, int] | None = None
    current: tuple[float, int] | None = None
    throttle: tuple[float, int] | None = None
    armed: bool = False
    #: the autopilot: its component id and MAV_AUTOPILOT (from its HEARTBEAT), None until heard
    compid: int | None = None
    autopilot: int | None = None
    #: compass instance -> the id of the sensor behind it (0: none in that slot), as read since the last boot
    ids: dict[int, int] = dataclasses.field(default_factory=dict)
    #: since when (wall ns) the ids are being read (samples wait), None when not; when they were last asked
    asking_ns: int | None = None
    asked_ns: int = 0
    #: when to ask again after giving up (wall ns), None when not given up
    retry_ns: int | None = None


@dataclasses.dataclass
class Pending:
    """A device's samples not yet sent: times (ns) and rows of (mag (3), acc (3), gyr (3), vel (3), current,
    throttle, hardware id (NaN while it is being read)); ``instance`` its compass instance."""

    sysid: int
    instance: int = 0
    times: list[int] = dataclasses.field(default_factory=list)
    rows: list[np.ndarray] = dataclasses.field(default_factory=list)
    first_ns: int = 0
    seq: int = 0
    last_t_ns: int = -1
    #: wall ns of its last sample (its silence frees its place: ``MavlinkStream.forget``)
    last_ns: int = 0
    gyro: GyroCheck = dataclasses.field(default_factory=GyroCheck)
