"""Whether a MAVLink compass's gyroscope is there (``magnet.autopilot.mavlink_stream``): ArduPilot fills SCALED_IMU2/3's
gyroscope with zeros when no IMU of that number sits beside the compass. Pure."""

from __future__ import annotations

import dataclasses

import numpy as np

#: a gyroscope reading exactly zero all the while the field turns this far (deg) is absent
ZERO_GYRO_TURN_DEG = 30.0


@dataclasses.dataclass
class GyroCheck:
    """Whether a device's gyroscope is there (module docstring): ``present`` once it read anything but exactly zero,
    ``absent`` once it read exactly zero while the field turned ``ZERO_GYRO_TURN_DEG`` from ``start`` (the field's
    direction, unit (3,), when the zeros began)."""

    present: bool = False
    absent: bool = False
    start: np.ndarray | None = None

    def usable(self, gyr_rads: np.ndarray | None, mag_ut: np.ndarray) -> bool:
        """Judge one sample's gyroscope (rad/s (3,), or None) with its field (uT (3,), not zero): whether to send
        it."""
        if gyr_rads is None:
            return False
        if gyr_rads.any():
            self.present, self.absent, self.start = True, False, None
            return True
        unit = mag_ut / float(np.linalg.norm(mag_ut))
        if self.start is None:
            self.start = unit
        elif float(unit @ self.start) < np.cos(np.radians(ZERO_GYRO_TURN_DEG)):
            self.present, self.absent = False, True
        return self.present
