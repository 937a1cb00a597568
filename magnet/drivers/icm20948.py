"""TDK InvenSense ICM-20948: accelerometer + gyroscope (I2C 0x68, or 0x69 with AD0 high) and, inside the same
package, an AKM AK09916 magnetometer reached directly at 0x0C once the ICM's bypass is on.

ICM-20948 registers (datasheet), in four banks chosen by REG_BANK_SEL 0x7F (bits 5:4; present in every bank):
- bank 0: WHO_AM_I 0x00 = 0xEA; USER_CTRL 0x03 (bit 5 I2C_MST_EN: off for bypass); PWR_MGMT_1 0x06 (bit 7 reset,
  bit 6 SLEEP, set at power-on; bits 2:0 clock, 1 = auto); PWR_MGMT_2 0x07 (0: every axis on); INT_PIN_CFG 0x0F
  (bit 1 BYPASS_EN: the auxiliary bus, with the AK09916, joins the host's); INT_ENABLE_1 0x11 (bit 0
  RAW_DATA_0_RDY_EN); INT_STATUS_1 0x1A (bit 0 RAW_DATA_0_RDY_INT, cleared when read); ACCEL_XOUT_H 0x2D ..
  ACCEL_ZOUT_L 0x32, GYRO_XOUT_H 0x33 .. GYRO_ZOUT_L 0x38, big-endian two's complement.
- bank 2: GYRO_SMPLRT_DIV 0x00 (gyro rate 1100 Hz / (1 + div)); GYRO_CONFIG_1 0x01 (bits 5:3 DLPF, bits 2:1
  GYRO_FS_SEL 250/500/1000/2000 deg/s = 131/65.5/32.8/16.4 LSB per deg/s, bit 0 FCHOICE); ACCEL_SMPLRT_DIV_1 0x10
  (bits 11:8) and _2 0x11 (bits 7:0) (accel rate 1125 Hz / (1 + div)); ACCEL_CONFIG 0x14 (bits 5:3 DLPF, bits 2:1
  ACCEL_FS_SEL 2/4/8/16 g = 16384/8192/4096/2048 LSB/g, bit 0 FCHOICE).

AK09916 (datasheet): as the AK09918C (``magnet.drivers.ak09918c``: ST1 0x10 DRDY, HXL 0x11.. little-endian, 0.15
uT/LSB, ST2 0x18 read to end a read, HOFL overflow, CNTL2 0x31 modes) with WIA2 0x01 = 0x09.

Axes: the accelerometer and gyroscope are z up (see ``magnet.drivers.inertial``); the AK09916's x is the ICM's x and
its y and z are the ICM's -y and -z, so it reads the body frame (x forward, y right, z down) directly when the package
lies flat, top up, x forward.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, Unpack

import numpy as np

from magnet.drivers.ak09918c import AK09918C, Mode
from magnet.drivers.base import NOT_READY, I2CBus, Reading, SensorError
from magnet.drivers.inertial import (
    Z_UP_TO_BODY,
    AccelGyro,
    ChipSpec,
    InertialOptions,
    NineAxis,
    choose,
    mounting,
    words,
)
from magnet.retry import RetryPolicy

DEFAULT_ADDRESS = 0x68
MAG_ADDRESS = 0x0C
REG_BANK_SEL = 0x7F
WHO_AM_I, USER_CTRL, PWR_MGMT_1, PWR_MGMT_2, INT_PIN_CFG, INT_ENABLE_1, INT_STATUS_1, ACCEL_XOUT_H = (
    0x00,
    0x03,
    0x06,
    0x07,
    0x0F,
    0x11,
    0x1A,
    0x2D,
)
GYRO_SMPLRT_DIV, GYRO_CONFIG_1, ACCEL_SMPLRT_DIV_1, ACCEL_SMPLRT_DIV_2, ACCEL_CONFIG = 0x00, 0x01, 0x10, 0x11, 0x14
CHIP_ID = 0xEA
PWR_CLOCK_AUTO = 0x01
BYPASS_EN = 0x02
RAW_DATA_RDY = 0x01
DLPF_ON = 0x01  # FCHOICE
DLPF_CFG = 3 << 3  # about 50 Hz bandwidth for both

#: full scale deg/s -> (GYRO_FS_SEL, LSB per deg/s)
GYRO_RANGES: dict[int, tuple[int, float]] = {250: (0, 131.0), 500: (1, 65.5), 1000: (2, 32.8), 2000: (3, 16.4)}
#: full scale g -> (ACCEL_FS_SEL, LSB per g)
ACCEL_RANGES: dict[int, tuple[int, float]] = {2: (0, 16384.0), 4: (1, 8192.0), 8: (2, 4096.0), 16: (3, 2048.0)}
#: output rate Hz -> sample-rate divider (gyroscope 1100 / (1 + div); the accelerometer's 1125 / (1 + div))
OUTPUT_RATES_HZ: dict[int, int] = {10: 109, 50: 21, 100: 10, 220: 4, 550: 1, 1100: 0}
#: AK09916 continuous-mode rate Hz -> mode
MAG_RATES_HZ: dict[int, Mode] = {
    10: Mode.CONTINUOUS_10HZ,
    20: Mode.CONTINUOUS_20HZ,
    50: Mode.CONTINUOUS_50HZ,
    100: Mode.CONTINUOUS_100HZ,
}
#: AK09916 axes -> ICM-20948 axes (x same, y and z reversed)
MAG_TO_ICM = np.diag([1.0, -1.0, -1.0])


class ICM20948AccelGyro(AccelGyro):
    """The accelerometer + gyroscope: checks WHO_AM_I, wakes the chip, turns the bypass on (so the AK09916 answers
    at 0x0C), sets full scales and rate; ``read()`` gives ``acc_ms2`` and ``gyr_rads`` when RAW_DATA_0_RDY is set."""

    SPEC = ChipSpec("ICM-20948", DEFAULT_ADDRESS, 100, ACCEL_RANGES, GYRO_RANGES, OUTPUT_RATES_HZ)

    def _configure(self) -> None:
        device = self.device
        device.write_byte(REG_BANK_SEL, 0 << 4)
        found = device.read_byte(WHO_AM_I)
        if found != CHIP_ID:
            raise SensorError(
                f"no ICM-20948 at {device.address:#04x}: WHO_AM_I reads {found:#04x}, expected 0xea "
                "(0x68 or 0x69 depending on AD0; an MPU-6050 reads 0x68 at register 0x75)"
            )
        device.write_byte(PWR_MGMT_1, PWR_CLOCK_AUTO)  # out of sleep
        device.write_byte(PWR_MGMT_2, 0x00)  # every axis on
        device.write_byte(USER_CTRL, 0x00)  # I2C master off, so that the bypass can work
        device.write_byte(INT_PIN_CFG, BYPASS_EN)
        device.write_byte(INT_ENABLE_1, RAW_DATA_RDY)
        device.write_byte(REG_BANK_SEL, 2 << 4)
        device.write_byte(GYRO_SMPLRT_DIV, self.rate_code)
        device.write_byte(GYRO_CONFIG_1, DLPF_CFG | (self.gyro_fs << 1) | DLPF_ON)
        device.write_byte(ACCEL_SMPLRT_DIV_1, self.rate_code >> 8)
        device.write_byte(ACCEL_SMPLRT_DIV_2, self.rate_code & 0xFF)
        device.write_byte(ACCEL_CONFIG, DLPF_CFG | (self.accel_fs << 1) | DLPF_ON)
        device.write_byte(REG_BANK_SEL, 0 << 4)

    def _read(self) -> Reading:
        if not self.device.read_byte(INT_STATUS_1) & RAW_DATA_RDY:
            return NOT_READY
        counts = words(self.device.read_block(ACCEL_XOUT_H, 12), big_endian=True)
        return self._scaled(counts[:3], counts[3:])


class AK09916(AK09918C):
    """The ICM-20948's magnetometer (reached in bypass mode): the AK09918C's register map, WIA2 = 0x09."""

    NAME = "AK09916"
    IDENTITY = (0x48, 0x09)

    def __init__(self, bus: I2CBus, address: int = MAG_ADDRESS, orientation: Any = None, **options: Any) -> None:
        """As ``AK09918C``; the axes are mapped to the body frame of the ICM-20948 package (module docstring)."""
        super().__init__(bus, address, orientation, **options)
        self.rotation = mounting(orientation, Z_UP_TO_BODY @ MAG_TO_ICM)


class ICM20948(NineAxis):
    """The whole package: accelerometer + gyroscope at ``acc_address`` (0x68/0x69) set up first (its bypass makes
    the AK09916 reachable), then the AK09916 at 0x0C; one ``orientation`` for the package (see the module docstring
    for the axes). ``read()`` gives ``mag_ut``, ``acc_ms2`` and ``gyr_rads`` in the body frame."""

    def __init__(
        self,
        bus: I2CBus,
        address: int = MAG_ADDRESS,
        orientation: Any = None,
        *,
        acc_address: int = DEFAULT_ADDRESS,
        mag_rate_hz: int = 100,
        retry: RetryPolicy | None = None,
        sleep: Callable[[float], None] | None = None,
        **inertial: Unpack[InertialOptions],
    ) -> None:
        mode = choose(mag_rate_hz, MAG_RATES_HZ, "magnetometer rate (Hz)", "AK09916")
        accel_gyro = ICM20948AccelGyro(bus, acc_address, orientation, retry=retry, sleep=sleep, **inertial)
        super().__init__(AK09916(bus, address, orientation, mode=mode, retry=retry, sleep=sleep), accel_gyro)
