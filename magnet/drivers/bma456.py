"""Bosch BMA456 three-axis accelerometer (I2C address 0x18, or 0x19 with SDO high), 16-bit (seed 004).

Registers (datasheet): CHIP_ID 0x00 = 0x16; STATUS 0x03 (bit 7 drdy_acc); ACC data 0x12..0x17 X, Y, Z little-endian
two's complement; ACC_CONF 0x40 (bit 7 performance mode, bits 6:4 bandwidth, bits 3:0 ODR, 0x08 = 100 Hz);
ACC_RANGE 0x41 (0..3 = 2, 4, 8, 16 g); PWR_CONF 0x7C (bit 0 advanced power save); PWR_CTRL 0x7D (bit 2 acc_en).

acc_ms2 = counts / LSB_PER_G[range] * 9.80665, LSB per g 16384, 8192, 4096 (8 g, the seed's), 2048.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np

from magnet.drivers.base import NOT_READY, I2CBus, Reading, Sensor, SensorError, to_signed
from magnet.retry import RetryPolicy
from magnet.units import STANDARD_GRAVITY_MS2

DEFAULT_ADDRESS = 0x18
REG_CHIP_ID, REG_STATUS, REG_DATA = 0x00, 0x03, 0x12
REG_ACC_CONF, REG_ACC_RANGE, REG_PWR_CONF, REG_PWR_CTRL = 0x40, 0x41, 0x7C, 0x7D
CHIP_ID = 0x16
STATUS_DRDY_ACC = 0x80
ACC_CONF_100HZ_AVG4_PERF = 0xA8
PWR_CTRL_ACC_EN = 0x04

#: range in g -> (register code, LSB per g)
RANGES: dict[int, tuple[int, float]] = {2: (0, 16384.0), 4: (1, 8192.0), 8: (2, 4096.0), 16: (3, 2048.0)}


class BMA456(Sensor):
    """Driver: checks CHIP_ID, switches power save off and the accelerometer on, sets the range (default 8 g)."""

    def __init__(
        self,
        bus: I2CBus,
        address: int = DEFAULT_ADDRESS,
        orientation: Any = None,
        *,
        range_g: int = 8,
        retry: RetryPolicy | None = None,
        sleep: Callable[[float], None] | None = None,
    ) -> None:
        if range_g not in RANGES:
            raise ValueError(f"BMA456 range must be one of {sorted(RANGES)} g, got {range_g}")
        self._attach(bus, address, orientation, retry, sleep)
        chip_id = self.device.read_byte(REG_CHIP_ID)
        if chip_id != CHIP_ID:
            raise SensorError(
                f"no BMA456 at {self.device.address:#04x}: CHIP_ID reads {chip_id:#04x}, expected "
                "0x16 (try address 0x19 if SDO is tied high)"
            )
        self.range_g = range_g
        self.device.write_byte(REG_PWR_CONF, 0x00)
        self.device.write_byte(REG_ACC_CONF, ACC_CONF_100HZ_AVG4_PERF)
        self.device.write_byte(REG_ACC_RANGE, RANGES[range_g][0])
        self.device.write_byte(REG_PWR_CTRL, PWR_CTRL_ACC_EN)

    def _read(self) -> Reading:
        if not self.device.read_byte(REG_STATUS) & STATUS_DRDY_ACC:
            return NOT_READY
        block = self.device.read_block(REG_DATA, 6)
        counts = np.array([to_signed(block[i] | (block[i + 1] << 8)) for i in (0, 2, 4)])
        return Reading(acc_ms2=counts / RANGES[self.range_g][1] * STANDARD_GRAVITY_MS2)
