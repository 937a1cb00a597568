"""Emulated InvenSense MPU-6050 (address 0x68), from the datasheet and register map, and the MPU-6050 beside an
HMC5883L or QMC5883L on one bus.

- WHO_AM_I 0x75 = 0x68. PWR_MGMT_1 0x6B: power-on 0x40 (SLEEP: no measurements), bit 7 DEVICE_RESET.
- Sample rate = (8 kHz if CONFIG 0x1A DLPF_CFG is 0 or 7, else 1 kHz) / (1 + SMPLRT_DIV 0x19).
- GYRO_CONFIG 0x1B FS_SEL bits 4:3 (131, 65.5, 32.8, 16.4 LSB per deg/s); ACCEL_CONFIG 0x1C AFS_SEL bits 4:3 (16384,
  8192, 4096, 2048 LSB/g). Codes saturate at the 16-bit limits.
- Data 0x3B..0x48: accel x, y, z, temperature (T = code / 340 + 36.53, at 25 C), gyro x, y, z, big-endian.
- INT_ENABLE 0x38 bit 0 DATA_RDY_EN; INT_STATUS 0x3A bit 0 DATA_RDY_INT set with each sample when enabled, cleared
  when INT_STATUS is read. INT_PIN_CFG 0x37 (bypass) is kept; the magnetometer beside it answers on the same bus.
- Axes: z up (``magnet.emulators.inertial``).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np

from magnet.emulators.base import EmulatedBus, FaultInjector, SourceTap
from magnet.emulators.inertial import INVENSENSE_ACCEL_LSB, INVENSENSE_GYRO_LSB, Z_UP, InertialDevice, board, put_words

_WRITABLE = frozenset({0x19, 0x1A, 0x1B, 0x1C, 0x37, 0x38, 0x6A, 0x6B, 0x6C})
_TEMPERATURE_CODE = round((25.0 - 36.53) * 340.0)


class MPU6050Emulator(InertialDevice):
    addresses = (0x68,)

    def _reset(self) -> None:
        self._power_on_reset({0x75: 0x68, 0x6B: 0x40})

    @property
    def period_s(self) -> float:
        base_hz = 8000.0 if self.regs[0x1A] & 0x07 in (0, 7) else 1000.0
        return (1 + self.regs[0x19]) / base_hz

    def _measure(self) -> None:
        accel, gyro = self.codes(
            INVENSENSE_ACCEL_LSB[(self.regs[0x1C] >> 3) & 0x03], INVENSENSE_GYRO_LSB[(self.regs[0x1B] >> 3) & 0x03]
        )
        put_words(self.regs, 0x3B, np.concatenate([accel, [_TEMPERATURE_CODE], gyro]), big_endian=True)
        if self.regs[0x38] & 0x01:
            self.regs[0x3A] |= 0x01
        self.unread = True

    def _update(self) -> None:
        if not self.regs[0x6B] & 0x40:
            self._measure_continuously(self.period_s)

    def _after_read(self, registers: list[int]) -> None:
        if 0x3A in registers:
            self.regs[0x3A] &= 0xFE
        if any(0x3B <= r <= 0x48 for r in registers):
            self.unread = False

    def _on_write(self, register: int, value: int) -> None:
        if register == 0x6B and value & 0x80:
            self._reset()
        elif register in _WRITABLE:
            self.regs[register] = value
            self._restart()


def mpu6050_with(magnetometer_class: type) -> Callable[..., EmulatedBus]:
    """A bus factory: an MPU-6050 and a ``magnetometer_class`` emulator side by side, both flat and top up on one
    board (the magnetometer's z-up axes are ``Z_UP @ rotation @ body``), fed by one source."""

    def bus(
        source: Any = None,
        *,
        acc_address: int = 0x68,
        rotation: Any = None,
        clock: Callable[[], float] | None = None,
        faults: FaultInjector | None = None,
        **mag_options: Any,
    ) -> EmulatedBus:
        tap, package = SourceTap(source), board(rotation)
        magnetometer = magnetometer_class(tap=tap, rotation=Z_UP @ package, clock=clock, **mag_options)
        inertial = MPU6050Emulator(tap=tap, address=acc_address, rotation=package, clock=clock)
        return EmulatedBus(magnetometer, inertial, faults=faults)

    return bus
