"""AKM AK09918C three-axis Hall magnetometer (I2C address 0x0C), 16-bit, 0.15 uT/LSB (seed 004).

Registers (datasheet): WIA1 0x00 = 0x48 (AKM), WIA2 0x01 = 0x0C (AK09918); ST1 0x10 (bit 0 DRDY, bit 1 DOR data
overrun); HXL..HZH 0x11..0x16 little-endian two's complement; TMPS 0x17; ST2 0x18 (bit 3 HOFL magnetic overflow:
|x|+|y|+|z| beyond 4912 uT); CNTL2 0x31 mode (0 power-down, 1 single, 2/4/6/8 continuous 10/20/50/100 Hz,
0x10 self-test); CNTL3 0x32 bit 0 soft reset. Reading ST2 ends a read and releases the data registers.

field_ut = counts * 0.15.
"""

from __future__ import annotations

import enum
from collections.abc import Callable
from typing import Any

import numpy as np

from magnet.drivers.base import NOT_READY, I2CBus, Reading, Sensor, SensorError, to_signed
from magnet.retry import RetryPolicy

DEFAULT_ADDRESS = 0x0C
REG_WIA1, REG_ST1, REG_CNTL2, REG_CNTL3 = 0x00, 0x10, 0x31, 0x32
IDENTITY = (0x48, 0x0C)
ST1_DRDY, ST1_DOR, ST2_HOFL = 0x01, 0x02, 0x08
UT_PER_COUNT = 0.15


class Mode(enum.IntEnum):
    POWER_DOWN = 0x00
    SINGLE = 0x01
    CONTINUOUS_10HZ = 0x02
    CONTINUOUS_20HZ = 0x04
    CONTINUOUS_50HZ = 0x06
    CONTINUOUS_100HZ = 0x08
    SELF_TEST = 0x10


class AK09918C(Sensor):
    """Driver: checks WIA1/WIA2, sets a continuous mode, reads ST1..ST2 (9 bytes) in one block per sample."""

    NAME = "AK09918C"
    IDENTITY = IDENTITY

    def __init__(
        self,
        bus: I2CBus,
        address: int = DEFAULT_ADDRESS,
        orientation: Any = None,
        *,
        mode: Mode = Mode.CONTINUOUS_100HZ,
        retry: RetryPolicy | None = None,
        sleep: Callable[[float], None] | None = None,
    ) -> None:
        self._attach(bus, address, orientation, retry, sleep)
        found = tuple(self.device.read_block(REG_WIA1, 2))
        if found != self.IDENTITY:
            raise SensorError(
                f"no {self.NAME} at {self.device.address:#04x}: WIA1/WIA2 read "
                f"{found[0]:#04x}/{found[1]:#04x}, expected "
                f"{self.IDENTITY[0]:#04x}/{self.IDENTITY[1]:#04x}"
            )
        self.mode = Mode(mode)
        self.device.write_byte(REG_CNTL2, int(Mode.POWER_DOWN))  # the datasheet: pass through power-down
        self.device.write_byte(REG_CNTL2, int(self.mode))

    def _read(self) -> Reading:
        block = self.device.read_block(REG_ST1, 9)  # ST1, HXL..HZH, TMPS, ST2: ends the read, releases the data
        status1, status2 = block[0], block[8]
        if not status1 & ST1_DRDY:
            return NOT_READY
        counts = np.array([to_signed(block[i] | (block[i + 1] << 8)) for i in (1, 3, 5)])
        if status2 & ST2_HOFL:
            return Reading(overflow=True, raw=counts)
        if self.mode == Mode.SINGLE:
            self.device.write_byte(REG_CNTL2, int(Mode.SINGLE))
        return Reading(mag_ut=counts * UT_PER_COUNT, raw=counts)
