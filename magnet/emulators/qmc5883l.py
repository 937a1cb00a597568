"""Emulated QST QMC5883L (address 0x0D), from the datasheet.

- 0x00..0x05 X, Y, Z little-endian; a channel beyond the 16-bit range saturates and sets OVL.
- 0x06 status: DRDY set when a new sample is placed, cleared when any data register is read; DOR set when a sample
  arrived while the previous one was unread (continuous mode), cleared by reading data; OVL as above.
- 0x07..0x08 temperature (100 LSB per degree, offset unknown: relative only).
- 0x09 control 1 (power-on 0x00 = standby): OSR 7:6, RNG 5:4 (2 G: 12000 LSB/G, 8 G: 3000 LSB/G), ODR 3:2
  (10/50/100/200 Hz), MODE 1:0 (standby, continuous). 0x0A control 2: SOFT_RST bit 7 restores the power-on values,
  ROL_PNT bit 6 makes the pointer roll over from 0x06 to 0x00. 0x0B SET/RESET period. 0x0D chip id 0xFF.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from magnet.emulators.base import MagnetometerDevice, to_bytes

_LSB_PER_GAUSS = {0b00: 12000.0, 0b01: 3000.0}
_ODR_HZ = (10.0, 50.0, 100.0, 200.0)
_POWER_ON = {0x0C: 0x01, 0x0D: 0xFF}


class QMC5883LEmulator(MagnetometerDevice):
    addresses = (0x0D,)

    def __init__(self, source: Any = None, **options: Any) -> None:
        """``options``: see ``MagnetometerDevice`` and ``SensorDevice``."""
        super().__init__(source, **options)
        self._reset()

    def _reset(self) -> None:
        self._power_on_reset(_POWER_ON)
        self.measurements = 0

    @property
    def continuous(self) -> bool:
        return self.regs[0x09] & 0x03 == 0b01

    def _measure(self) -> None:
        lsb = _LSB_PER_GAUSS.get((self.regs[0x09] >> 4) & 0x03, 3000.0)
        scale = lsb * self.sensitivity()
        counts = np.round(self.rotation @ self.tap.mag() / 100.0 * scale)
        overflow = bool(np.any((counts > 32767) | (counts < -32768)))
        counts = np.clip(counts, -32768, 32767).astype(int)
        for axis in range(3):
            high, low = to_bytes(counts[axis])
            self.regs[2 * axis], self.regs[2 * axis + 1] = low, high
        high, low = to_bytes(round((self.temperature_c - 25.0) * 100))
        self.regs[0x07], self.regs[0x08] = low, high
        status = 0x01 | (0x02 if overflow else 0) | (0x04 if self.unread else 0)
        self.regs[0x06] = status
        self.unread = True
        self.measurements += 1

    def _update(self) -> None:
        if self.continuous:
            self._measure_continuously(1.0 / _ODR_HZ[(self.regs[0x09] >> 2) & 0x03])

    def _after_read(self, registers: list[int]) -> None:
        if any(r <= 0x05 for r in registers):
            self.regs[0x06] &= ~0x05 & 0xFF  # DRDY and DOR clear on a data read
            self.unread = False

    def _on_write(self, register: int, value: int) -> None:
        if register == 0x0A and value & 0x80:
            self._reset()
            return
        if register in (0x09, 0x0A, 0x0B):
            self.regs[register] = value
        if register == 0x09:
            self.next_due = None

    def _next_pointer(self, register: int) -> int:
        if self.regs[0x0A] & 0x40 and register == 0x06:
            return 0x00
        return (register + 1) & 0xFF
