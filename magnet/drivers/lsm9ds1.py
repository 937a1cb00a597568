"""ST LSM9DS1: accelerometer + gyroscope (I2C 0x6B, or 0x6A with SDO_AG low) and magnetometer (0x1E, or 0x1C with
SDO_M low) in one package.

Accelerometer + gyroscope registers (datasheet): WHO_AM_I 0x0F = 0x68; CTRL_REG1_G 0x10 (ODR_G bits 7:5: power-down,
14.9, 59.5, 119, 238, 476, 952 Hz; FS_G bits 4:3: 245/500/2000 deg/s = 8.75/17.5/70 mdps/LSB); STATUS_REG 0x17
(bit 0 XLDA, bit 1 GDA); OUT_X_L_G 0x18..0x1D; CTRL_REG4 0x1E and CTRL_REG5_XL 0x1F (axis enables bits 5:3);
CTRL_REG6_XL 0x20 (ODR_XL bits 7:5, used alone when the gyroscope is off; FS_XL bits 4:3: 2, 16, 4, 8 g = 0.061,
0.732, 0.122, 0.244 mg/LSB); CTRL_REG8 0x22 (bit 6 BDU, bit 2 IF_ADD_INC: multi-byte reads go up through the
registers, on at power-on; bit 0 SW_RESET); OUT_X_L_XL 0x28..0x2D. Data little-endian two's complement. With the
gyroscope on, both run at the gyroscope's rate.

Magnetometer registers: WHO_AM_I_M 0x0F = 0x3D; CTRL_REG1_M 0x20 (bit 7 TEMP_COMP, OM bits 6:5 x/y performance,
DO bits 4:2: 0.625 .. 80 Hz); CTRL_REG2_M 0x21 (FS bits 6:5: 4/8/12/16 gauss = 0.14/0.29/0.43/0.58 mgauss/LSB, bit 2
SOFT_RST); CTRL_REG3_M 0x22 (MD bits 1:0: continuous 0, single 1, power-down 2/3 at power-on); CTRL_REG4_M 0x23 (OMZ
bits 3:2); CTRL_REG5_M 0x24 (bit 6 BDU); STATUS_REG_M 0x27 (bit 3 ZYXDA, bit 7 ZYXOR); OUT_X_L_M 0x28..0x2D little-
endian. A multi-byte read of the magnetometer needs bit 7 of the sub-address set.

Axes: the accelerometer and gyroscope are z up (``magnet.drivers.inertial``); the magnetometer's x points the other
way (its y and z are the accelerometer's), so in the body frame of a package lying flat, top up, x forward the field
is (-x, -y, -z) of the magnetometer's codes.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, Unpack

import numpy as np

from magnet.drivers.base import NOT_READY, I2CBus, Reading, Sensor, SensorError
from magnet.drivers.inertial import (
    Z_UP_TO_BODY,
    AccelGyro,
    ChipSpec,
    InertialOptions,
    NineAxis,
    choose,
    mounting,
    saturated,
    words,
)
from magnet.retry import RetryPolicy

DEFAULT_ADDRESS = 0x1E  # magnetometer
DEFAULT_AG_ADDRESS = 0x6B  # accelerometer + gyroscope
WHO_AM_I = 0x0F
AG_ID, MAG_ID = 0x68, 0x3D
CTRL_REG1_G, STATUS_REG, OUT_X_L_G, CTRL_REG4, CTRL_REG5_XL, CTRL_REG6_XL, CTRL_REG8, OUT_X_L_XL = (
    0x10,
    0x17,
    0x18,
    0x1E,
    0x1F,
    0x20,
    0x22,
    0x28,
)
CTRL_REG1_M, CTRL_REG2_M, CTRL_REG3_M, CTRL_REG4_M, CTRL_REG5_M, STATUS_REG_M, OUT_X_L_M = (
    0x20,
    0x21,
    0x22,
    0x23,
    0x24,
    0x27,
    0x28,
)
XLDA, GDA = 0x01, 0x02
ZYXDA = 0x08
AXES_ON = 0x38
BDU, IF_ADD_INC = 0x40, 0x04
AUTO_INCREMENT_M = 0x80
TEMP_COMP, XY_ULTRA_HIGH, Z_ULTRA_HIGH = 0x80, 0x60, 0x0C

#: full scale deg/s -> (FS_G, mdps per LSB)
GYRO_RANGES: dict[int, tuple[int, float]] = {245: (0b00, 8.75), 500: (0b01, 17.5), 2000: (0b11, 70.0)}
#: full scale g -> (FS_XL, mg per LSB)
ACCEL_RANGES: dict[int, tuple[int, float]] = {2: (0b00, 0.061), 4: (0b10, 0.122), 8: (0b11, 0.244), 16: (0b01, 0.732)}
#: output rate Hz (gyroscope, and so the accelerometer) -> ODR_G
OUTPUT_RATES_HZ: dict[float, int] = {14.9: 1, 59.5: 2, 119: 3, 238: 4, 476: 5, 952: 6}
#: magnetometer full scale gauss -> (FS, mgauss per LSB)
MAG_RANGES: dict[int, tuple[int, float]] = {4: (0b00, 0.14), 8: (0b01, 0.29), 12: (0b10, 0.43), 16: (0b11, 0.58)}
#: magnetometer output rate Hz -> DO
MAG_RATES_HZ: dict[float, int] = {0.625: 0, 1.25: 1, 2.5: 2, 5: 3, 10: 4, 20: 5, 40: 6, 80: 7}
#: magnetometer axes -> accelerometer/gyroscope axes (x reversed: the datasheet's axis figure as we read it; the
#: one place to change should a board show otherwise)
MAG_TO_AG = np.diag([-1.0, 1.0, 1.0])


class LSM9DS1AccelGyro(AccelGyro):
    """The accelerometer + gyroscope: checks WHO_AM_I, sets block update, auto-increment, axes, full scales and the
    rate; ``read()`` gives ``acc_ms2`` and ``gyr_rads`` once both have new data (XLDA and GDA)."""

    SPEC = ChipSpec("LSM9DS1", DEFAULT_AG_ADDRESS, 119, ACCEL_RANGES, GYRO_RANGES, OUTPUT_RATES_HZ, milli_per_lsb=True)

    def _configure(self) -> None:
        found = self.device.read_byte(WHO_AM_I)
        if found != AG_ID:
            raise SensorError(
                f"no LSM9DS1 accelerometer/gyroscope at {self.device.address:#04x}: WHO_AM_I reads "
                f"{found:#04x}, expected 0x68 (0x6b or 0x6a depending on SDO_AG)"
            )
        self.device.write_byte(CTRL_REG8, BDU | IF_ADD_INC)
        self.device.write_byte(CTRL_REG4, AXES_ON)
        self.device.write_byte(CTRL_REG5_XL, AXES_ON)
        self.device.write_byte(CTRL_REG6_XL, (self.rate_code << 5) | (self.accel_fs << 3))
        self.device.write_byte(CTRL_REG1_G, (self.rate_code << 5) | (self.gyro_fs << 3))

    def _read(self) -> Reading:
        if self.device.read_byte(STATUS_REG) & (XLDA | GDA) != XLDA | GDA:
            return NOT_READY
        gyro = words(self.device.read_block(OUT_X_L_G, 6), big_endian=False)
        accel = words(self.device.read_block(OUT_X_L_XL, 6), big_endian=False)
        return self._scaled(accel, gyro)


class LSM9DS1Magnetometer(Sensor):
    """The magnetometer: checks WHO_AM_I_M, temperature-compensated ultra-high-performance continuous mode at
    ``rate_hz`` and ``range_gauss``; ``read()`` gives ``mag_ut`` when ZYXDA is set (overflow when a channel is at
    the end of its range). Its axes are mapped to the body frame of the package (module docstring)."""

    def __init__(
        self,
        bus: I2CBus,
        address: int = DEFAULT_ADDRESS,
        orientation: Any = None,
        *,
        range_gauss: int = 4,
        rate_hz: float = 80,
        retry: RetryPolicy | None = None,
        sleep: Callable[[float], None] | None = None,
    ) -> None:
        self.fs, self.mgauss_per_lsb = choose(range_gauss, MAG_RANGES, "magnetometer range (gauss)", "LSM9DS1")
        self.odr = choose(rate_hz, MAG_RATES_HZ, "magnetometer rate (Hz)", "LSM9DS1")
        self._attach(bus, address, orientation, retry, sleep)
        self.rotation = mounting(orientation, Z_UP_TO_BODY @ MAG_TO_AG)
        found = self.device.read_byte(WHO_AM_I)
        if found != MAG_ID:
            raise SensorError(
                f"no LSM9DS1 magnetometer at {self.device.address:#04x}: WHO_AM_I_M reads "
                f"{found:#04x}, expected 0x3d (0x1e or 0x1c depending on SDO_M)"
            )
        self.device.write_byte(CTRL_REG1_M, TEMP_COMP | XY_ULTRA_HIGH | (self.odr << 2))
        self.device.write_byte(CTRL_REG2_M, self.fs << 5)
        self.device.write_byte(CTRL_REG4_M, Z_ULTRA_HIGH)
        self.device.write_byte(CTRL_REG5_M, BDU)
        self.device.write_byte(CTRL_REG3_M, 0x00)  # continuous

    def _read(self) -> Reading:
        if not self.device.read_byte(STATUS_REG_M) & ZYXDA:
            return NOT_READY
        counts = words(self.device.read_block(OUT_X_L_M | AUTO_INCREMENT_M, 6), big_endian=False)
        if saturated(counts):
            return Reading(overflow=True, raw=counts)
        return Reading(mag_ut=counts * self.mgauss_per_lsb / 10.0, raw=counts)  # 1 mgauss = 0.1 uT


class LSM9DS1(NineAxis):
    """The whole package: magnetometer at ``address`` (0x1E/0x1C) and accelerometer + gyroscope at ``acc_address``
    (0x6B/0x6A), one ``orientation`` for the package (see the module docstring for the axes)."""

    def __init__(
        self,
        bus: I2CBus,
        address: int = DEFAULT_ADDRESS,
        orientation: Any = None,
        *,
        acc_address: int = DEFAULT_AG_ADDRESS,
        range_gauss: int = 4,
        mag_rate_hz: float = 80,
        retry: RetryPolicy | None = None,
        sleep: Callable[[float], None] | None = None,
        **inertial: Unpack[InertialOptions],
    ) -> None:
        accel_gyro = LSM9DS1AccelGyro(bus, acc_address, orientation, retry=retry, sleep=sleep, **inertial)
        magnetometer = LSM9DS1Magnetometer(
            bus, address, orientation, range_gauss=range_gauss, rate_hz=mag_rate_hz, retry=retry, sleep=sleep
        )
        super().__init__(magnetometer, accel_gyro)
