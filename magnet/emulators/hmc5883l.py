"""Emulated Honeywell HMC5883L (address 0x1E), from the datasheet's description of the chip.

- Config A 0x00 (power-on 0x10): averaging bits 6:5, rate bits 4:2 (0.75..75 Hz), bias bits 1:0 (normal, +, -).
- Config B 0x01 (power-on 0x20): gain bits 7:5. The first measurement after a gain change still uses the old gain.
- Mode 0x02 (power-on 0x01): continuous, single (then idle: MD bits set), idle.
- Data 0x03..0x08: X, Z, Y big-endian; a channel outside -2048..2047 reads -4096.
- Status 0x09: RDY set when all six data registers are written, cleared once they have all been read. LOCK set when
  some but not all data registers, or the Mode register, have been read; while locked, new data are not placed.
  LOCK clears when all six are read, or Mode or Config A is written.
- Identification 0x0A..0x0C 'H', '4', '3'. The pointer goes 0x08 -> 0x03 and 0x0C -> 0x00, else up by one.
- Bias modes: the output is the straps' field alone (x, y +1.16 Ga, z +1.08 Ga, negated for negative bias); if the
  external field plus the bias would saturate a channel, that channel reads -4096.
"""

from __future__ import annotations

from typing import Any, ClassVar

import numpy as np

from magnet.emulators.base import MagnetometerDevice, to_bytes

SINGLE_MEASUREMENT_S = 0.006


class AMRMagnetometerEmulator(MagnetometerDevice):
    """Shared machinery of the Honeywell-style AMR magnetometers (HMC5883L, LSM303DLH magnetometer)."""

    #: register slot 0..2 -> axis index (x 0, y 1, z 2)
    data_axes: tuple[int, int, int] = (0, 2, 1)
    #: gain code -> LSB per gauss for (x, y, z); None = code not valid
    lsb_per_gauss: tuple[tuple[float, float, float] | None, ...] = ()
    rates_hz: tuple[float, ...] = (0.75, 1.5, 3.0, 7.5, 15.0, 30.0, 75.0, 75.0)
    bias_field_ga = np.array([1.16, 1.16, 1.08])
    adc_limits = (-2048, 2047)
    overflow_code = -4096
    power_on: ClassVar[dict[int, int]] = {
        0x00: 0x10,
        0x01: 0x20,
        0x02: 0x01,
        0x0A: ord("H"),
        0x0B: ord("4"),
        0x0C: ord("3"),
    }
    writable = frozenset({0x00, 0x01, 0x02})
    data_registers = frozenset(range(0x03, 0x09))

    def __init__(self, source: Any = None, **options: Any) -> None:
        """``options``: see ``MagnetometerDevice`` and ``SensorDevice``."""
        super().__init__(source, **options)
        for register, value in self.power_on.items():
            self.regs[register] = value
        self.active_gain = self.regs[0x01] >> 5
        self.unread = False  # data placed and not yet fully read
        self.read_so_far: set[int] = set()
        self.locked = False
        self.ready = False
        self.single_due: float | None = None
        self.continuous_next: float | None = None
        self.measurements = 0

    # ---- measurement
    @property
    def mode(self) -> int:
        return self.regs[0x02] & 0x03

    def _counts(self) -> np.ndarray:
        gain = self.lsb_per_gauss[self.active_gain] or self.lsb_per_gauss[1]
        scale = np.asarray(gain) * self.sensitivity()
        external_ga = self.rotation @ self.tap.mag() / 100.0
        bias = self.regs[0x00] & 0x03
        if bias in (1, 2):
            sign = 1.0 if bias == 1 else -1.0
            bias_counts = np.round(sign * self.bias_field_ga * scale)
            total = np.round((external_ga + sign * self.bias_field_ga) * scale)
            saturated = (total < self.adc_limits[0]) | (total > self.adc_limits[1])
            counts = np.where(saturated, self.overflow_code, bias_counts)
        else:
            counts = np.round(external_ga * scale)
            saturated = (counts < self.adc_limits[0]) | (counts > self.adc_limits[1])
            counts = np.where(saturated, self.overflow_code, counts)
        return counts.astype(int)

    def _measure(self) -> None:
        counts = self._counts()
        self.active_gain = self.regs[0x01] >> 5  # the new gain takes effect from the next measurement on
        self.measurements += 1
        if self.locked:
            return
        for slot, axis in enumerate(self.data_axes):
            high, low = to_bytes(counts[axis])
            self.regs[0x03 + 2 * slot], self.regs[0x04 + 2 * slot] = high, low
        self.unread = True
        self.ready = True
        self._set_status()

    def _set_status(self) -> None:
        self.regs[0x09] = (0x02 if self.locked else 0) | (0x01 if self.ready else 0)

    def _update(self) -> None:
        now = self.now()
        if self.mode == 0:
            if now is None:
                if not self.unread:
                    self._measure()
            elif self.continuous_next is not None and now >= self.continuous_next:
                period = 1.0 / self.rates_hz[(self.regs[0x00] >> 2) & 0x07]
                self._measure()
                missed = int((now - self.continuous_next) // period)
                self.continuous_next += (missed + 1) * period
        elif self.single_due is not None and (now is None or now >= self.single_due):
            self.single_due = None
            self._measure()
            self.regs[0x02] = (self.regs[0x02] & ~0x03) | 0x03  # back to idle

    # ---- register side effects
    def _on_read(self, register: int) -> int:
        if register == 0x02:
            self.locked = True
            self._set_status()
        return self.regs[register]

    def _after_read(self, registers: list[int]) -> None:
        data = self.data_registers.intersection(registers)
        if not data:
            return
        self.read_so_far |= data
        if self.read_so_far >= self.data_registers:
            self.read_so_far.clear()
            self.locked = False
            self.ready = False
            self.unread = False
        else:
            self.locked = True
        self._set_status()

    def _on_write(self, register: int, value: int) -> None:
        if register not in self.writable:
            return
        self.regs[register] = value
        if register in (0x00, 0x02):
            self.locked = False
            self.read_so_far.clear()
            self._set_status()
        if register == 0x00 or register == 0x01:
            self.unread = False  # continuous mode: the next measurement follows the new configuration
        if register == 0x02:
            self._start_mode()

    def _start_mode(self) -> None:
        now = self.now()
        self.unread = False
        self.continuous_next = None
        if self.mode == 0:
            if now is not None:
                self.continuous_next = now + 1.0 / self.rates_hz[(self.regs[0x00] >> 2) & 0x07]
        elif self.mode == 1:
            self.single_due = None if now is None else now + SINGLE_MEASUREMENT_S
            if now is None:
                self.single_due = float("-inf")

    def _next_pointer(self, register: int) -> int:
        if register == 0x08:
            return 0x03
        if register >= 0x0C:
            return 0x00
        return register + 1


class HMC5883LEmulator(AMRMagnetometerEmulator):
    """HMC5883L: gains 1370, 1090, 820, 660, 440, 390, 330, 230 LSB/Ga on every axis; data X, Z, Y."""

    addresses = (0x1E,)
    data_axes = (0, 2, 1)
    lsb_per_gauss = tuple((g, g, g) for g in (1370.0, 1090.0, 820.0, 660.0, 440.0, 390.0, 330.0, 230.0))
