"""QST QMC5883L three-axis magnetometer (I2C address 0x0D), the usual chip on "HMC5883L" modules sold today.

Registers (datasheet): 0x00..0x05 X, Y, Z little-endian 16-bit two's complement; 0x06 status (bit 0 DRDY, bit 1 OVL
overflow, bit 2 DOR data skipped); 0x07..0x08 temperature; 0x09 control 1: OSR bits 7:6 (512, 256, 128, 64), range
bits 5:4 (2 G, 8 G), ODR bits 3:2 (10, 50, 100, 200 Hz), mode bits 1:0 (standby, continuous); 0x0A control 2
(bit 7 soft reset, bit 6 pointer roll-over, bit 0 interrupt disable); 0x0B SET/RESET period (0x01 recommended);
0x0D chip id 0xFF.

field_ut = counts / LSB_PER_GAUSS[range] * 100, LSB per gauss 12000 (2 G) or 3000 (8 G).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from typing import Any

import numpy as np

from magnet.drivers.base import NOT_READY, I2CBus, Reading, Sensor, SensorError, to_signed
from magnet.retry import RetryPolicy

DEFAULT_ADDRESS = 0x0D
REG_DATA, REG_STATUS, REG_CONTROL1, REG_CONTROL2, REG_PERIOD, REG_CHIP_ID = 0x00, 0x06, 0x09, 0x0A, 0x0B, 0x0D
CHIP_ID = 0xFF
STATUS_DRDY, STATUS_OVL, STATUS_DOR = 0x01, 0x02, 0x04

#: range in gauss -> (bits, LSB per gauss)
RANGES: dict[int, tuple[int, float]] = {2: (0b00, 12000.0), 8: (0b01, 3000.0)}
OVERSAMPLING: dict[int, int] = {512: 0b00, 256: 0b01, 128: 0b10, 64: 0b11}
OUTPUT_RATE_HZ: dict[int, int] = {10: 0b00, 50: 0b01, 100: 0b10, 200: 0b11}
MODE_CONTINUOUS = 0b01


@dataclasses.dataclass(frozen=True)
class QMC5883LSettings:
    """Full-scale range in gauss (2 or 8), output rate in Hz (10/50/100/200), oversampling ratio (512..64)."""

    range_gauss: int = 8
    rate_hz: int = 100
    oversampling: int = 512

    def __post_init__(self) -> None:
        for value, table, what in (
            (self.range_gauss, RANGES, "range (gauss)"),
            (self.rate_hz, OUTPUT_RATE_HZ, "output rate (Hz)"),
            (self.oversampling, OVERSAMPLING, "oversampling"),
        ):
            if value not in table:
                raise ValueError(f"QMC5883L {what} must be one of {sorted(table)}, got {value}")

    @property
    def control1(self) -> int:
        return (
            (OVERSAMPLING[self.oversampling] << 6)
            | (RANGES[self.range_gauss][0] << 4)
            | (OUTPUT_RATE_HZ[self.rate_hz] << 2)
            | MODE_CONTINUOUS
        )


class QMC5883L(Sensor):
    """Driver: checks the chip id, sets continuous mode, reads Status then the six data bytes when DRDY."""

    def __init__(
        self,
        bus: I2CBus,
        address: int = DEFAULT_ADDRESS,
        orientation: Any = None,
        *,
        settings: QMC5883LSettings | None = None,
        retry: RetryPolicy | None = None,
        sleep: Callable[[float], None] | None = None,
    ) -> None:
        self._attach(bus, address, orientation, retry, sleep)
        chip_id = self.device.read_byte(REG_CHIP_ID)
        if chip_id != CHIP_ID:
            raise SensorError(
                f"no QMC5883L at {self.device.address:#04x}: chip id register 0x0D reads "
                f"{chip_id:#04x}, expected 0xff (check the address with i2cdetect)"
            )
        self.settings = settings or QMC5883LSettings()
        self.device.write_byte(REG_CONTROL2, 0x40)  # pointer roll-over on, interrupt pin enabled
        self.device.write_byte(REG_PERIOD, 0x01)  # SET/RESET period, as the datasheet recommends
        self.device.write_byte(REG_CONTROL1, self.settings.control1)

    @property
    def ut_per_count(self) -> float:
        return 100.0 / RANGES[self.settings.range_gauss][1]

    def _read(self) -> Reading:
        status = self.device.read_byte(REG_STATUS)
        if not status & STATUS_DRDY:
            return NOT_READY
        block = self.device.read_block(REG_DATA, 6)
        counts = np.array([to_signed(block[i] | (block[i + 1] << 8)) for i in (0, 2, 4)])
        if status & STATUS_OVL:
            return Reading(overflow=True, raw=counts)
        return Reading(mag_ut=counts * self.ut_per_count, raw=counts)
