"""Emulated ST LSM303DLH: magnetometer (0x1E) and accelerometer (0x18) sharing one package and one source.

Magnetometer: the Honeywell-style register map (see ``magnet.emulators.hmc5883l``) with data X, Y, Z, gains per
code 1..7 of 1055/950, 795/710, 635/570, 430/385, 375/335, 320/285, 230/205 LSB/gauss (x and y / z), power-on Mode
0x03 (sleep).
Accelerometer: CTRL_REG1_A 0x20 (power-on 0x07: powered down; PM bits 7:5 = 001 normal), rate bits 4:3 (50, 100,
400, 1000 Hz); CTRL_REG4_A 0x23 (FS bits 5:4: 2 g 1 mg/digit, 4 g 2 mg/digit, 8 g 3.9 mg/digit); STATUS_REG_A 0x27
(bit 3 ZYXDA, cleared when data are read); OUT 0x28..0x2D little-endian, 12-bit left-justified. The sub-address
auto-increments only when its bit 7 is set; otherwise a multi-byte read repeats the same register.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, ClassVar

import numpy as np
import numpy.typing as npt

from magnet.emulators.base import STANDARD_GRAVITY_MS2, EmulatedBus, FaultInjector, SensorDevice, SourceTap
from magnet.emulators.hmc5883l import AMRMagnetometerEmulator

_MG_PER_DIGIT = {0b00: 1.0, 0b01: 2.0, 0b11: 3.9}
_ACC_RATE_HZ = (50.0, 100.0, 400.0, 1000.0)


class LSM303DLHMagEmulator(AMRMagnetometerEmulator):
    addresses = (0x1E,)
    data_axes = (0, 1, 2)
    lsb_per_gauss = (
        None,
        (1055.0, 1055.0, 950.0),
        (795.0, 795.0, 710.0),
        (635.0, 635.0, 570.0),
        (430.0, 430.0, 385.0),
        (375.0, 375.0, 335.0),
        (320.0, 320.0, 285.0),
        (230.0, 230.0, 205.0),
    )
    power_on: ClassVar[dict[int, int]] = {
        0x00: 0x10,
        0x01: 0x20,
        0x02: 0x03,
        0x0A: ord("H"),
        0x0B: ord("4"),
        0x0C: ord("3"),
    }


class LSM303DLHAccEmulator(SensorDevice):
    addresses = (0x18,)

    def __init__(self, source: Any = None, **options: Any) -> None:
        """``options``: see ``SensorDevice``."""
        super().__init__(source, **options)
        self.regs[0x20] = 0x07
        self.unread = False
        self.next_due: float | None = None

    @property
    def powered(self) -> bool:
        return (self.regs[0x20] >> 5) & 0x07 != 0

    def _measure(self) -> None:
        mg_per_digit = _MG_PER_DIGIT.get((self.regs[0x23] >> 4) & 0x03, 1.0)
        digits = np.clip(
            np.round(self.rotation @ self.tap.acc() / STANDARD_GRAVITY_MS2 * 1000.0 / mg_per_digit), -2048, 2047
        ).astype(int)
        for axis in range(3):
            raw = (int(digits[axis]) << 4) & 0xFFFF
            self.regs[0x28 + 2 * axis], self.regs[0x29 + 2 * axis] = raw & 0xFF, raw >> 8
        self.regs[0x27] = 0x08 | (0x80 if self.unread else 0)
        self.unread = True

    def _update(self) -> None:
        if self.powered:
            self._measure_continuously(1.0 / _ACC_RATE_HZ[(self.regs[0x20] >> 3) & 0x03])

    def _translate(self, register: int) -> tuple[int, bool]:
        return register & 0x7F, bool(register & 0x80)

    def _after_read(self, registers: list[int]) -> None:
        if any(0x28 <= r <= 0x2D for r in registers):
            self.regs[0x27] = 0
            self.unread = False

    def _on_write(self, register: int, value: int) -> None:
        if register in (0x20, 0x21, 0x22, 0x23, 0x24):
            self.regs[register] = value
            if register == 0x20:
                self.next_due = None


class LSM303DLHEmulator(EmulatedBus):
    """Both halves on one bus with one source; ``.mag`` and ``.acc`` are the two chips."""

    def __init__(
        self,
        source: Any = None,
        *,
        acc_address: int = 0x18,
        gain_error: npt.ArrayLike = (0.0, 0.0, 0.0),
        temperature_c: float = 25.0,
        tempco_per_k: float = 0.0,
        rotation: Any = None,
        clock: Callable[[], float] | None = None,
        faults: FaultInjector | None = None,
    ) -> None:
        tap = SourceTap(source)
        self.mag = LSM303DLHMagEmulator(
            tap=tap,
            gain_error=gain_error,
            temperature_c=temperature_c,
            tempco_per_k=tempco_per_k,
            rotation=rotation,
            clock=clock,
        )
        self.acc = LSM303DLHAccEmulator(tap=tap, address=acc_address, rotation=rotation, clock=clock)
        super().__init__(self.mag, self.acc, faults=faults)
