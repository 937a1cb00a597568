"""What the accelerometer + gyroscope emulators share: the chip's axes and the conversion to 16-bit codes.

The InvenSense and ST inertial chips mark their axes right-handed with z up out of the package top: a package lying
flat, top up, x forward has its chip axes at (x, -y, -z) of the body frame (x forward, y right, z down), so a level,
still device reads +1 g on the chip's z. ``rotation`` (3x3, as for every emulator) maps the body to the package's
frame (identity: the package lies flat, top up, x forward); the chip's axes are then ``Z_UP @ rotation @ body``.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from magnet.emulators.base import STANDARD_GRAVITY_MS2, SensorDevice

#: body (or package) axes -> the axes of a z-up chip lying flat, top up, x forward
Z_UP = np.diag([1.0, -1.0, -1.0])
#: the InvenSense chips' (MPU-6050, ICM-20948) codes per g and per deg/s, by full-scale setting (bits FS_SEL)
INVENSENSE_ACCEL_LSB = (16384.0, 8192.0, 4096.0, 2048.0)
INVENSENSE_GYRO_LSB = (131.0, 65.5, 32.8, 16.4)


def board(rotation: Any) -> np.ndarray:
    """The board's rotation (3, 3) from the body: ``rotation`` as floats, identity when None."""
    return np.eye(3) if rotation is None else np.asarray(rotation, dtype=float)


def int16(values: np.ndarray) -> np.ndarray:
    """Rounded and saturated to the 16-bit two's complement range."""
    return np.clip(np.round(values), -32768, 32767).astype(int)


def put_words(regs: bytearray, start: int, counts: np.ndarray, big_endian: bool) -> None:
    """Write 16-bit codes from register ``start`` on, two bytes each."""
    for i, value in enumerate(counts):
        raw = int(value) & 0xFFFF
        high, low = raw >> 8, raw & 0xFF
        regs[start + 2 * i], regs[start + 2 * i + 1] = (high, low) if big_endian else (low, high)


class InertialDevice(SensorDevice):
    """An accelerometer + gyroscope chip fed by the source's specific force and angular rate."""

    def __init__(self, source: Any = None, **options: Any) -> None:
        """``options``: see ``SensorDevice``; ``rotation`` maps the body to the package (module docstring)."""
        super().__init__(source, **options)
        self.chip_from_body = Z_UP @ self.rotation
        self._reset()

    def _reset(self) -> None:  # pragma: no cover - abstract
        """Power-on state of the chip's registers."""
        raise NotImplementedError

    def _restart(self) -> None:
        """A configuration write restarts sampling: the next sample comes at the new settings (and, with no clock,
        at the next transaction, whatever was left unread)."""
        self.next_due = None
        self.unread = False

    def sample(self) -> tuple[np.ndarray, np.ndarray]:
        """(specific force in g (3,), angular rate in deg/s (3,)) in the chip's axes, from the latest source sample."""
        acc_g = self.chip_from_body @ self.tap.acc() / STANDARD_GRAVITY_MS2
        gyr_dps = self.chip_from_body @ self.tap.gyr() * (180.0 / math.pi)
        return acc_g, gyr_dps

    def codes(self, lsb_per_g: float, lsb_per_dps: float) -> tuple[np.ndarray, np.ndarray]:
        """(accelerometer, gyroscope) 16-bit codes (3,) each of the latest source sample at these sensitivities."""
        acc_g, gyr_dps = self.sample()
        return int16(acc_g * lsb_per_g), int16(gyr_dps * lsb_per_dps)
