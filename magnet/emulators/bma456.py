"""Emulated Bosch BMA456 accelerometer (address 0x18), from the datasheet.

- CHIP_ID 0x00 = 0x16. STATUS 0x03 bit 7 drdy_acc: set when a sample is placed, cleared when acceleration data are
  read. ACC data 0x12..0x17 X, Y, Z little-endian 16-bit two's complement, saturating.
- ACC_CONF 0x40 (power-on 0xA8), ACC_RANGE 0x41 (power-on 0x01 = 4 g; 0..3 = 2, 4, 8, 16 g: 16384, 8192, 4096, 2048
  LSB/g). PWR_CONF 0x7C (power-on 0x03, advanced power save), PWR_CTRL 0x7D (power-on 0x00; bit 2 acc_en: no data
  until set). CMD 0x7E: 0xB6 soft reset.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from magnet.emulators.base import STANDARD_GRAVITY_MS2, SensorDevice

_LSB_PER_G = (16384.0, 8192.0, 4096.0, 2048.0)
_POWER_ON = {0x00: 0x16, 0x40: 0xA8, 0x41: 0x01, 0x7C: 0x03, 0x7D: 0x00}
_ODR_HZ = {
    1: 0.78125,
    2: 1.5625,
    3: 3.125,
    4: 6.25,
    5: 12.5,
    6: 25.0,
    7: 50.0,
    8: 100.0,
    9: 200.0,
    10: 400.0,
    11: 800.0,
    12: 1600.0,
}


class BMA456Emulator(SensorDevice):
    addresses = (0x18,)

    def __init__(self, source: Any = None, **options: Any) -> None:
        """``options``: see ``SensorDevice``."""
        super().__init__(source, **options)
        self._reset()

    def _reset(self) -> None:
        self._power_on_reset(_POWER_ON)

    @property
    def enabled(self) -> bool:
        return bool(self.regs[0x7D] & 0x04)

    def _measure(self) -> None:
        lsb = _LSB_PER_G[self.regs[0x41] & 0x03]
        counts = np.clip(np.round(self.rotation @ self.tap.acc() / STANDARD_GRAVITY_MS2 * lsb), -32768, 32767)
        for axis in range(3):
            raw = int(counts[axis]) & 0xFFFF
            self.regs[0x12 + 2 * axis], self.regs[0x13 + 2 * axis] = raw & 0xFF, raw >> 8
        self.regs[0x03] |= 0x80
        self.unread = True

    def _update(self) -> None:
        if self.enabled:
            self._measure_continuously(1.0 / _ODR_HZ.get(self.regs[0x40] & 0x0F, 100.0))

    def _after_read(self, registers: list[int]) -> None:
        if any(0x12 <= r <= 0x17 for r in registers):
            self.regs[0x03] &= 0x7F
            self.unread = False

    def _on_write(self, register: int, value: int) -> None:
        if register == 0x7E and value == 0xB6:
            self._reset()
        elif register in (0x40, 0x41, 0x7C, 0x7D):
            self.regs[register] = value
