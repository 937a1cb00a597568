"""Emulated AKM AK09918C (address 0x0C), from the datasheet.

- WIA1 0x00 = 0x48, WIA2 0x01 = 0x0C. ST1 0x10: DRDY (bit 0) set when a sample is placed; DOR (bit 1) set when a
  sample was skipped because the previous one was not read; both clear when ST2 is read (the end of a read).
- HXL..HZH 0x11..0x16 little-endian, 0.15 uT/LSB, saturating at +-32752; TMPS 0x17 (dummy); ST2 0x18: HOFL (bit 3)
  when |x| + |y| + |z| >= 4912 uT.
- While a read is in progress (ST1 or data read, ST2 not yet) new samples are not placed (data protection).
- CNTL2 0x31: 0 power-down, 1 single (back to power-down after it), 2/4/6/8 continuous 10/20/50/100 Hz, 0x10 self
  test (a fixed internal field, then power-down). CNTL3 0x32 bit 0: soft reset.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, ClassVar

import numpy as np

from magnet.emulators.base import EmulatedBus, FaultInjector, MagnetometerDevice, SourceTap

UT_PER_LSB = 0.15
_CONTINUOUS_HZ = {0x02: 10.0, 0x04: 20.0, 0x06: 50.0, 0x08: 100.0}
_SELF_TEST_COUNTS = np.array([30, -40, -400])


class AK09918CEmulator(MagnetometerDevice):
    addresses = (0x0C,)
    power_on: ClassVar[dict[int, int]] = {0x00: 0x48, 0x01: 0x0C}  # WIA1, WIA2

    def __init__(self, source: Any = None, **options: Any) -> None:
        """``options``: see ``MagnetometerDevice`` and ``SensorDevice``."""
        super().__init__(source, **options)
        self._reset()

    def _reset(self) -> None:
        self._power_on_reset(self.power_on)
        self.protected = False
        self.pending = False
        self.measurements = 0

    @property
    def mode(self) -> int:
        return self.regs[0x31] & 0x1F

    def _measure(self) -> None:
        if self.mode == 0x10:
            counts = _SELF_TEST_COUNTS.copy()
        else:
            field = self.rotation @ self.tap.mag()
            sens = self.sensitivity()
            counts = np.clip(np.round(field * sens / UT_PER_LSB), -32752, 32752).astype(int)
        self.measurements += 1
        if self.protected:
            self.regs[0x10] |= 0x02  # skipped: data overrun
            return
        overflow = np.sum(np.abs(counts)) * UT_PER_LSB >= 4912.0
        for axis in range(3):
            raw = int(counts[axis]) & 0xFFFF
            self.regs[0x11 + 2 * axis], self.regs[0x12 + 2 * axis] = raw & 0xFF, raw >> 8
        self.regs[0x18] = 0x08 if overflow else 0x00
        self.regs[0x10] = (self.regs[0x10] & 0x02) | (0x02 if self.unread else 0) | 0x01
        self.unread = True

    def _update(self) -> None:
        if self.pending and self.mode in (0x01, 0x10):
            self.pending = False
            self._measure()
            self.regs[0x31] = 0x00
        elif self.mode in _CONTINUOUS_HZ:
            self._measure_continuously(1.0 / _CONTINUOUS_HZ[self.mode], may_measure=not self.protected)

    def _after_read(self, registers: list[int]) -> None:
        if any(0x10 <= r <= 0x17 for r in registers):
            self.protected = True
        if 0x18 in registers:
            self.protected = False
            self.unread = False
            self.regs[0x10] &= ~0x03 & 0xFF

    def _on_write(self, register: int, value: int) -> None:
        if register == 0x32 and value & 0x01:
            self._reset()
        elif register == 0x31:
            self.regs[0x31] = value & 0x1F
            self.next_due = None
            self.pending = self.mode in (0x01, 0x10)
        elif register == 0x30:
            self.regs[0x30] = value


def ak09918c_bma456_bus(
    source: Any = None,
    *,
    acc_address: int = 0x18,
    rotation: Any = None,
    clock: Callable[[], float] | None = None,
    faults: FaultInjector | None = None,
    **mag_options: Any,
) -> EmulatedBus:
    """An AK09918C and a BMA456 on one bus, fed by one source (as on the seed 004 board)."""
    from magnet.emulators.bma456 import BMA456Emulator

    tap = SourceTap(source)
    return EmulatedBus(
        AK09918CEmulator(tap=tap, rotation=rotation, clock=clock, **mag_options),
        BMA456Emulator(tap=tap, address=acc_address, rotation=rotation, clock=clock),
        faults=faults,
    )
