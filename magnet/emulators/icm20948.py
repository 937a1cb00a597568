"""Emulated TDK InvenSense ICM-20948 (address 0x68) with its AK09916 magnetometer (0x0C), from the datasheets.

ICM-20948:
- Four register banks of 128 registers; REG_BANK_SEL 0x7F (bits 5:4) in every bank picks the bank.
- Bank 0: WHO_AM_I 0x00 = 0xEA; USER_CTRL 0x03 (bit 5 I2C_MST_EN); PWR_MGMT_1 0x06 power-on 0x41 (SLEEP: no
  measurements; bit 7 DEVICE_RESET); PWR_MGMT_2 0x07; INT_PIN_CFG 0x0F (bit 1 BYPASS_EN); INT_ENABLE_1 0x11 (bit 0
  RAW_DATA_0_RDY_EN); INT_STATUS_1 0x1A (bit 0 RAW_DATA_0_RDY_INT, set with each sample when enabled, cleared when
  read); ACCEL_XOUT_H 0x2D..0x32, GYRO_XOUT_H 0x33..0x38 big-endian, saturating.
- Bank 2: GYRO_SMPLRT_DIV 0x00 (samples at 1100 Hz / (1 + div)); GYRO_CONFIG_1 0x01 (power-on 0x01; FS bits 2:1:
  131, 65.5, 32.8, 16.4 LSB per deg/s); ACCEL_SMPLRT_DIV_1/2 0x10/0x11; ACCEL_CONFIG 0x14 (power-on 0x01; FS bits 2:1:
  16384, 8192, 4096, 2048 LSB/g).
- The AK09916 sits on the ICM's auxiliary bus: the host reaches it at 0x0C only while BYPASS_EN is set and the ICM's
  I2C master is off; otherwise 0x0C does not answer (a NACK).
AK09916: the AK09918C's behaviour (``magnet.emulators.ak09918c``) with WIA2 0x01 = 0x09.
Axes: the ICM is z up (``magnet.emulators.inertial``); the AK09916's x, y, z are the ICM's x, -y, -z.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, ClassVar

import numpy as np

from magnet.emulators.ak09918c import AK09918CEmulator
from magnet.emulators.base import EmulatedBus, FaultInjector, RegisterDevice, SourceTap, _nack
from magnet.emulators.inertial import INVENSENSE_ACCEL_LSB, INVENSENSE_GYRO_LSB, Z_UP, InertialDevice, board, put_words

_POWER_ON = {0: {0x00: 0xEA, 0x06: 0x41}, 2: {0x01: 0x01, 0x14: 0x01}}
_READ_ONLY_BANK0 = frozenset({0x00, 0x1A, *range(0x2D, 0x3B)})
#: ICM axes -> AK09916 axes
MAG_FROM_ICM = np.diag([1.0, -1.0, -1.0])


class ICM20948Chip(InertialDevice):
    """The accelerometer + gyroscope part, with its register banks."""

    addresses = (0x68,)

    def _reset(self) -> None:
        self._power_on_reset({})
        self.banks = [bytearray(128) for _ in range(4)]
        for bank, values in _POWER_ON.items():
            for register, value in values.items():
                self.banks[bank][register] = value
        self.bank = 0

    @property
    def bypass(self) -> bool:
        """The auxiliary bus (the AK09916) is joined to the host's."""
        bank0 = self.banks[0]
        return bool(bank0[0x0F] & 0x02) and not bank0[0x03] & 0x20

    def _measure(self) -> None:
        bank0, bank2 = self.banks[0], self.banks[2]
        accel, gyro = self.codes(
            INVENSENSE_ACCEL_LSB[(bank2[0x14] >> 1) & 0x03], INVENSENSE_GYRO_LSB[(bank2[0x01] >> 1) & 0x03]
        )
        put_words(bank0, 0x2D, np.concatenate([accel, gyro]), big_endian=True)
        if bank0[0x11] & 0x01:
            bank0[0x1A] |= 0x01
        self.unread = True

    def _update(self) -> None:
        if not self.banks[0][0x06] & 0x40:
            self._measure_continuously((1 + self.banks[2][0x00]) / 1100.0)

    def _on_read(self, register: int) -> int:
        if register == 0x7F:
            return self.bank << 4
        return self.banks[self.bank][register] if register < 0x80 else 0

    def _after_read(self, registers: list[int]) -> None:
        if self.bank != 0:
            return
        if 0x1A in registers:
            self.banks[0][0x1A] &= 0xFE
        if any(0x2D <= r <= 0x38 for r in registers):
            self.unread = False

    def _on_write(self, register: int, value: int) -> None:
        if register == 0x7F:
            self.bank = (value >> 4) & 0x03
        elif self.bank == 0 and register == 0x06 and value & 0x80:
            self._reset()
        elif register < 0x80 and not (self.bank == 0 and register in _READ_ONLY_BANK0):
            self.banks[self.bank][register] = value
            self._restart()


class AK09916Emulator(AK09918CEmulator):
    power_on: ClassVar[dict[int, int]] = {0x00: 0x48, 0x01: 0x09}  # WIA1, WIA2


class ICM20948Emulator(EmulatedBus):
    """The package on one bus with one source; ``.imu`` and ``.mag`` are the two chips. ``address`` moves the ICM
    (0x68 or 0x69); ``mag_options`` go to the AK09916 (``gain_error``, ``temperature_c``, ``tempco_per_k``)."""

    def __init__(
        self,
        source: Any = None,
        *,
        address: int = 0x68,
        rotation: Any = None,
        clock: Callable[[], float] | None = None,
        faults: FaultInjector | None = None,
        **mag_options: Any,
    ) -> None:
        tap, package = SourceTap(source), board(rotation)
        self.imu = ICM20948Chip(tap=tap, address=address, rotation=package, clock=clock)
        self.mag = AK09916Emulator(tap=tap, rotation=MAG_FROM_ICM @ Z_UP @ package, clock=clock, **mag_options)
        super().__init__(self.imu, self.mag, faults=faults)

    def _device(self, address: int) -> RegisterDevice:
        device = super()._device(address)
        if device is self.mag and not self.imu.bypass:
            raise _nack(address)
        return device
