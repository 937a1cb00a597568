"""What the accelerometer + gyroscope drivers share: the package frame, setting tables, data words, and the
nine-axis combination of a magnetometer with an accelerometer + gyroscope.

Frames. The InvenSense and ST inertial chips mark their axes right-handed with z up out of the package top (a chip
lying flat, top up, reads +1 g on z). The drivers map that to the body frame (x forward, y right, z down) for a
package lying flat, top up, with its x mark forward: body = (x, -y, -z), ``Z_UP_TO_BODY``. A magnetometer in the same
package has its own axes (see each chip); the driver maps it to the same body frame, so a package read with the
default orientation gives field, specific force and rate in one frame. ``orientation`` (as for every driver, see
``magnet.drivers.base.orientation_matrix``) then turns the package in the body: body = orientation @ package frame.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping
from typing import Any

import numpy as np

from magnet.drivers.base import Combined, Reading, Sensor, orientation_matrix, to_signed

#: chip axes with z up out of the package -> body axes of a package lying flat, top up, x forward
Z_UP_TO_BODY = np.diag([1.0, -1.0, -1.0])
RAD_PER_DEG = math.pi / 180.0
INT16_LIMITS = (-32768, 32767)


def mounting(orientation: Any, chip_to_package: np.ndarray) -> np.ndarray:
    """Chip axes -> body: ``orientation_matrix(orientation) @ chip_to_package`` (3, 3)."""
    return orientation_matrix(orientation) @ chip_to_package


def choose(value: Any, table: Mapping[Any, Any], what: str, chip: str) -> Any:
    """``table[value]``, or ValueError naming the chip, the setting and the values allowed."""
    try:
        return table[value]
    except (KeyError, TypeError):
        raise ValueError(
            f"{chip} {what} must be one of {', '.join(f'{k:g}' for k in sorted(table))}, got {value!r}"
        ) from None


def words(block: list[int], big_endian: bool) -> np.ndarray:
    """Signed 16-bit words (len(block) // 2,) from bytes, high byte first when ``big_endian``."""
    pairs = [(block[i], block[i + 1]) for i in range(0, len(block) - 1, 2)]
    return np.array([to_signed((a << 8) | b if big_endian else (b << 8) | a) for a, b in pairs])


def saturated(counts: np.ndarray) -> bool:
    """A 16-bit channel at either end of its range: the quantity is beyond the full scale."""
    return bool(np.any((counts <= INT16_LIMITS[0]) | (counts >= INT16_LIMITS[1])))


class NineAxis(Combined):
    """A magnetometer with an accelerometer + gyroscope: the magnetometer sets the pace (a reading is ready when it
    has a new field), the inertial chip gives its latest sample. When the inertial chip has nothing new yet (it runs
    slower than it is polled) its previous sample is held; when it saturated, ``acc_ms2`` and ``gyr_rads`` are None
    for that reading (a saturated rate is never passed on)."""

    def __init__(self, magnetometer: Sensor, inertial: Sensor) -> None:
        super().__init__(magnetometer, inertial)
        self._last: Reading | None = None

    def read(self) -> Reading:
        mag = self.magnetometer.read()
        imu = self.accelerometer.read()
        if imu.ready:
            self._last = imu
        held = self._last
        if held is None or held.overflow:
            return dataclasses.replace(mag, acc_ms2=None, gyr_rads=None)
        return dataclasses.replace(mag, acc_ms2=held.acc_ms2, gyr_rads=held.gyr_rads)
