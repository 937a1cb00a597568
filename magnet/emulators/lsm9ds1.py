"""Emulated ST LSM9DS1: accelerometer + gyroscope (0x6B) and magnetometer (0x1E) in one package, one source.

Accelerometer + gyroscope:
- WHO_AM_I 0x0F = 0x68. CTRL_REG1_G 0x10 (power-on 0: gyroscope off; ODR_G bits 7:5 = 14.9, 59.5, 119, 238, 476,
  952 Hz; FS_G bits 4:3: 245, 500, -, 2000 deg/s at 8.75, 17.5, -, 70 mdps/LSB). CTRL_REG6_XL 0x20 (ODR_XL bits 7:5 =
  10, 50, 119, 238, 476, 952 Hz, used when the gyroscope is off; FS_XL bits 4:3: 2, 16, 4, 8 g at 0.061, 0.732, 0.122,
  0.244 mg/LSB). With the gyroscope on, both sample at the gyroscope's rate; with both off, nothing is measured.
- STATUS_REG 0x17 (mirrored at 0x27): XLDA bit 0, GDA bit 1, set with each sample, each cleared when its output
  registers are read. OUT_X_L_G 0x18..0x1D, OUT_X_L_XL 0x28..0x2D little-endian, saturating.
- CTRL_REG8 0x22 (power-on 0x04): bit 2 IF_ADD_INC, multi-byte reads go up through the registers only while set;
  bit 0 SW_RESET.
Magnetometer:
- WHO_AM_I_M 0x0F = 0x3D. CTRL_REG1_M 0x20 (power-on 0x10; DO bits 4:2 = 0.625 .. 80 Hz); CTRL_REG2_M 0x21 (FS bits
  6:5: 4, 8, 12, 16 gauss at 0.14, 0.29, 0.43, 0.58 mgauss/LSB; bit 2 SOFT_RST); CTRL_REG3_M 0x22 (power-on 0x03: MD
  continuous 0, single 1 (then power-down), power-down 2/3).
- STATUS_REG_M 0x27: ZYXDA bit 3 (and XDA, YDA, ZDA) with each sample, ZYXOR bit 7 when a sample overwrote an unread
  one; cleared when the data are read. OUT_X_L_M 0x28..0x2D little-endian, saturating. Multi-byte reads go up only
  when bit 7 of the sub-address is set.
Axes: accelerometer and gyroscope z up (``magnet.emulators.inertial``); the magnetometer's x is the other way
(-x, y, z of the accelerometer's axes).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np

from magnet.emulators.base import EmulatedBus, FaultInjector, MagnetometerDevice, SourceTap
from magnet.emulators.inertial import Z_UP, InertialDevice, board, int16, put_words

_GYRO_ODR_HZ = (0.0, 14.9, 59.5, 119.0, 238.0, 476.0, 952.0, 0.0)
_ACCEL_ODR_HZ = (0.0, 10.0, 50.0, 119.0, 238.0, 476.0, 952.0, 0.0)
_MDPS_PER_LSB = (8.75, 17.5, 8.75, 70.0)  # code 2 is not available; the chip keeps 245 deg/s
_MG_PER_LSB = (0.061, 0.732, 0.122, 0.244)
_AG_WRITABLE = frozenset({*range(0x10, 0x14), *range(0x1E, 0x25), 0x2E, *range(0x30, 0x38)})
_MAG_ODR_HZ = (0.625, 1.25, 2.5, 5.0, 10.0, 20.0, 40.0, 80.0)
_MGAUSS_PER_LSB = (0.14, 0.29, 0.43, 0.58)
_MAG_WRITABLE = frozenset({*range(0x05, 0x0B), 0x20, 0x21, 0x22, 0x23, 0x24, 0x30, 0x32, 0x33})
#: accelerometer/gyroscope axes -> magnetometer axes
MAG_FROM_AG = np.diag([-1.0, 1.0, 1.0])


class LSM9DS1AccelGyroEmulator(InertialDevice):
    addresses = (0x6B,)

    def _reset(self) -> None:
        self._power_on_reset({0x0F: 0x68, 0x1E: 0x38, 0x1F: 0x38, 0x22: 0x04})
        self.unread_gyro = self.unread_accel = False

    def _restart(self) -> None:
        super()._restart()
        self.unread_gyro = self.unread_accel = False

    @property
    def rate_hz(self) -> float:
        gyro = _GYRO_ODR_HZ[self.regs[0x10] >> 5]
        return gyro or _ACCEL_ODR_HZ[self.regs[0x20] >> 5]

    def _measure(self) -> None:
        acc_g, gyr_dps = self.sample()
        status = self.regs[0x17]
        if _GYRO_ODR_HZ[self.regs[0x10] >> 5]:
            put_words(
                self.regs,
                0x18,
                int16(gyr_dps * 1000.0 / _MDPS_PER_LSB[(self.regs[0x10] >> 3) & 0x03]),
                big_endian=False,
            )
            status |= 0x02
            self.unread_gyro = True
        put_words(self.regs, 0x28, int16(acc_g * 1000.0 / _MG_PER_LSB[(self.regs[0x20] >> 3) & 0x03]), big_endian=False)
        self.regs[0x17] = self.regs[0x27] = status | 0x01
        self.unread_accel = True
        self.unread = True

    def _update(self) -> None:
        if self.rate_hz:
            self._measure_continuously(1.0 / self.rate_hz)

    def _translate(self, register: int) -> tuple[int, bool]:
        return register & 0x7F, bool(self.regs[0x22] & 0x04)

    def _after_read(self, registers: list[int]) -> None:
        if any(0x18 <= r <= 0x1D for r in registers):
            self.unread_gyro = False
            self.regs[0x17] &= 0xFD
        if any(0x28 <= r <= 0x2D for r in registers):
            self.unread_accel = False
            self.regs[0x17] &= 0xFE
        self.regs[0x27] = self.regs[0x17]
        self.unread = self.unread_gyro or self.unread_accel

    def _on_write(self, register: int, value: int) -> None:
        if register == 0x22 and value & 0x01:
            self._reset()
        elif register in _AG_WRITABLE:
            self.regs[register] = value
            self._restart()


class LSM9DS1MagEmulator(MagnetometerDevice):
    addresses = (0x1E,)

    def __init__(self, source: Any = None, **options: Any) -> None:
        """``options``: see ``MagnetometerDevice``; ``rotation`` maps the body to the magnetometer's axes."""
        super().__init__(source, **options)
        self._reset()

    def _reset(self) -> None:
        self._power_on_reset({0x0F: 0x3D, 0x20: 0x10, 0x22: 0x03})
        self.measurements = 0

    @property
    def mode(self) -> int:
        return self.regs[0x22] & 0x03

    def _measure(self) -> None:
        field = self.rotation @ self.tap.mag() * self.sensitivity()
        counts = int16(field * 10.0 / _MGAUSS_PER_LSB[(self.regs[0x21] >> 5) & 0x03])  # 1 uT = 10 mgauss
        put_words(self.regs, 0x28, counts, big_endian=False)
        self.regs[0x27] = 0x0F | (0xF0 if self.unread else 0x00)
        self.unread = True
        self.measurements += 1

    def _update(self) -> None:
        if self.mode == 0x00:
            self._measure_continuously(1.0 / _MAG_ODR_HZ[(self.regs[0x20] >> 2) & 0x07])
        elif self.mode == 0x01:
            self._measure()
            self.regs[0x22] |= 0x03  # single conversion done: power-down

    def _translate(self, register: int) -> tuple[int, bool]:
        return register & 0x7F, bool(register & 0x80)

    def _after_read(self, registers: list[int]) -> None:
        if any(0x28 <= r <= 0x2D for r in registers):
            self.unread = False
            self.regs[0x27] = 0x00

    def _on_write(self, register: int, value: int) -> None:
        if register == 0x21 and value & 0x04:
            self._reset()
        elif register in _MAG_WRITABLE:
            self.regs[register] = value
            self.next_due = None


class LSM9DS1Emulator(EmulatedBus):
    """Both parts on one bus with one source; ``.ag`` and ``.mag`` are the two chips. ``acc_address`` and
    ``address`` move them (0x6A, 0x1C); ``mag_options`` go to the magnetometer."""

    def __init__(
        self,
        source: Any = None,
        *,
        address: int = 0x1E,
        acc_address: int = 0x6B,
        rotation: Any = None,
        clock: Callable[[], float] | None = None,
        faults: FaultInjector | None = None,
        **mag_options: Any,
    ) -> None:
        tap, package = SourceTap(source), board(rotation)
        self.ag = LSM9DS1AccelGyroEmulator(tap=tap, address=acc_address, rotation=package, clock=clock)
        self.mag = LSM9DS1MagEmulator(
            tap=tap, address=address, rotation=MAG_FROM_AG @ Z_UP @ package, clock=clock, **mag_options
        )
        super().__init__(self.ag, self.mag, faults=faults)
