"""ST LSM303DLH: AMR magnetometer (I2C 0x1E) and accelerometer (0x18, or 0x19 with SA0 high) in one package.

Magnetometer (datasheet): CRA_REG_M 0x00 (rate bits 4:2, 0.75..75 Hz; bias bits 1:0), CRB_REG_M 0x01 (gain bits 7:5,
codes 1..7 = +-1.3 .. +-8.1 gauss), MR_REG_M 0x02 (0 continuous, 1 single, 2/3 sleep), data 0x03..0x08 X, Y, Z
big-endian 12-bit (-4096 = overflow), SR_REG_M 0x09 (bit 0 DRDY, bit 1 LOCK), IRA..IRC 0x0A..0x0C = 'H', '4', '3'.
Unlike the HMC5883L the data come X, Y, Z, and z has its own gain:

    field_ut = counts / LSB_PER_GAUSS[gain][axis] * 100

Accelerometer: CTRL_REG1_A 0x20 (power mode bits 7:5, rate bits 4:3, axis enables 2:0), CTRL_REG4_A 0x23 (bit 7
BDU, bits 5:4 full scale 2/4/8 g), STATUS_REG_A 0x27 (bit 3 ZYXDA), OUT_X_L_A 0x28..OUT_Z_H_A 0x2D little-endian,
12-bit left-justified; a multi-byte read needs bit 7 of the sub-address set.

    acc_ms2 = (raw16 >> 4) * MG_PER_DIGIT[scale] / 1000 * 9.80665
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np

from magnet.drivers.base import NOT_READY, Combined, I2CBus, Reading, Sensor, SensorError, to_signed
from magnet.retry import RetryPolicy
from magnet.units import STANDARD_GRAVITY_MS2

DEFAULT_ADDRESS = 0x1E
DEFAULT_ACC_ADDRESS = 0x18
IDENTITY = b"H43"
OVERFLOW = -4096

#: gain code -> LSB per gauss (x, y, z); code 0 is not valid
LSB_PER_GAUSS: dict[int, tuple[float, float, float]] = {
    1: (1055.0, 1055.0, 950.0),
    2: (795.0, 795.0, 710.0),
    3: (635.0, 635.0, 570.0),
    4: (430.0, 430.0, 385.0),
    5: (375.0, 375.0, 335.0),
    6: (320.0, 320.0, 285.0),
    7: (230.0, 230.0, 205.0),
}
#: full scale in g -> (FS bits, mg per digit of the 12-bit value)
ACC_SCALES: dict[int, tuple[int, float]] = {2: (0b00, 1.0), 4: (0b01, 2.0), 8: (0b11, 3.9)}
RATE_75HZ = 0x06 << 2
AUTO_INCREMENT = 0x80


class LSM303DLHMagnetometer(Sensor):
    """The magnetometer half: identity check, 75 Hz continuous at ``gain`` (1..7), one six-byte read per sample."""

    def __init__(
        self,
        bus: I2CBus,
        address: int = DEFAULT_ADDRESS,
        orientation: Any = None,
        *,
        gain: int = 1,
        retry: RetryPolicy | None = None,
        sleep: Callable[[float], None] | None = None,
    ) -> None:
        if gain not in LSB_PER_GAUSS:
            raise ValueError(f"LSM303DLH magnetometer gain must be 1..7, got {gain}")
        self._attach(bus, address, orientation, retry, sleep)
        found = bytes(self.device.read_block(0x0A, 3))
        if found != IDENTITY:
            raise SensorError(
                f"no LSM303DLH magnetometer at {self.device.address:#04x}: identification reads "
                f"{found!r}, expected {IDENTITY!r}"
            )
        self.gain = gain
        # as on the HMC5883L, the first measurement after a gain change is at the old gain: drop it
        self._discard = int(self.device.read_byte(0x01) >> 5 != gain)
        self.device.write_byte(0x00, RATE_75HZ)
        self.device.write_byte(0x01, gain << 5)
        self.device.write_byte(0x02, 0x00)

    def _read(self) -> Reading:
        if not self.device.read_byte(0x09) & 0x01:
            return NOT_READY
        block = self.device.read_block(0x03, 6)
        counts = np.array([to_signed((block[i] << 8) | block[i + 1]) for i in (0, 2, 4)])
        if self._discard:
            self._discard -= 1
            return NOT_READY
        if np.any(counts == OVERFLOW):
            return Reading(overflow=True, raw=counts)
        return Reading(mag_ut=counts / np.array(LSB_PER_GAUSS[self.gain]) * 100.0, raw=counts)


class LSM303DLHAccelerometer(Sensor):
    """The accelerometer half: normal mode 50 Hz, all axes, block data update, full scale ``scale_g``."""

    def __init__(
        self,
        bus: I2CBus,
        address: int = DEFAULT_ACC_ADDRESS,
        orientation: Any = None,
        *,
        scale_g: int = 2,
        retry: RetryPolicy | None = None,
        sleep: Callable[[float], None] | None = None,
    ) -> None:
        if scale_g not in ACC_SCALES:
            raise ValueError(f"LSM303DLH accelerometer full scale must be one of {sorted(ACC_SCALES)} g")
        self._attach(bus, address, orientation, retry, sleep)
        self.scale_g = scale_g
        self.device.write_byte(0x20, 0x27)
        self.device.write_byte(0x23, 0x80 | (ACC_SCALES[scale_g][0] << 4))
        if self.device.read_byte(0x20) != 0x27:
            raise SensorError(
                f"no LSM303DLH accelerometer at {self.device.address:#04x}: CTRL_REG1_A did not "
                "keep its value (try the other address, 0x18 or 0x19)"
            )

    def _read(self) -> Reading:
        if not self.device.read_byte(0x27) & 0x08:
            return NOT_READY
        block = self.device.read_block(0x28 | AUTO_INCREMENT, 6)
        counts = np.array([to_signed(block[i] | (block[i + 1] << 8)) >> 4 for i in (0, 2, 4)])
        return Reading(acc_ms2=counts * ACC_SCALES[self.scale_g][1] / 1000.0 * STANDARD_GRAVITY_MS2)


class LSM303DLH(Combined):
    """Both halves as one sensor: ``read()`` gives ``mag_ut`` and ``acc_ms2``; the package's axes are shared, so
    one ``orientation`` applies to both."""

    def __init__(
        self,
        bus: I2CBus,
        address: int = DEFAULT_ADDRESS,
        orientation: Any = None,
        *,
        acc_address: int = DEFAULT_ACC_ADDRESS,
        gain: int = 1,
        scale_g: int = 2,
        retry: RetryPolicy | None = None,
        sleep: Callable[[float], None] | None = None,
    ) -> None:
        super().__init__(
            LSM303DLHMagnetometer(bus, address, orientation, gain=gain, retry=retry, sleep=sleep),
            LSM303DLHAccelerometer(bus, acc_address, orientation, scale_g=scale_g, retry=retry, sleep=sleep),
        )
