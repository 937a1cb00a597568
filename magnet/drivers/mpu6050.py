"""InvenSense MPU-6050 accelerometer + gyroscope (I2C 0x68, or 0x69 with AD0 high), and its pairing with an
HMC5883L or QMC5883L magnetometer on the same bus (as on GY-86/GY-87 style boards).

Registers (datasheet / register map): SMPLRT_DIV 0x19 (sample rate = gyroscope output rate / (1 + div), the output
rate being 1 kHz with the low-pass filter on, 8 kHz off); CONFIG 0x1A (DLPF_CFG bits 2:0); GYRO_CONFIG 0x1B (FS_SEL
bits 4:3: 250/500/1000/2000 deg/s = 131/65.5/32.8/16.4 LSB per deg/s); ACCEL_CONFIG 0x1C (AFS_SEL bits 4:3: 2/4/8/16
g = 16384/8192/4096/2048 LSB/g); INT_PIN_CFG 0x37 (bit 1 I2C_BYPASS_EN: an auxiliary-bus magnetometer joins the
host's bus); INT_ENABLE 0x38 (bit 0 DATA_RDY_EN); INT_STATUS 0x3A (bit 0 DATA_RDY_INT, cleared when read);
ACCEL_XOUT_H 0x3B .. ACCEL_ZOUT_L 0x40, TEMP_OUT 0x41-0x42, GYRO_XOUT_H 0x43 .. GYRO_ZOUT_L 0x48, big-endian two's
complement; PWR_MGMT_1 0x6B (bit 7 DEVICE_RESET, bit 6 SLEEP, set at power-on; CLKSEL bits 2:0, 1 = gyro x PLL);
WHO_AM_I 0x75 = 0x68.

Axes: z up (``magnet.drivers.inertial``). The magnetometer beside it is taken to lie flat, top up, with its x mark
along the MPU-6050's x (both mapped to the body frame the same way); ``orientation`` turns the board.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

from magnet.drivers.base import NOT_READY, I2CBus, Reading, Sensor, SensorError
from magnet.drivers.inertial import Z_UP_TO_BODY, AccelGyro, ChipSpec, NineAxis, mounting, words
from magnet.retry import RetryPolicy

DEFAULT_ADDRESS = 0x68
SMPLRT_DIV, CONFIG, GYRO_CONFIG, ACCEL_CONFIG, INT_PIN_CFG, INT_ENABLE, INT_STATUS, ACCEL_XOUT_H = (
    0x19,
    0x1A,
    0x1B,
    0x1C,
    0x37,
    0x38,
    0x3A,
    0x3B,
)
PWR_MGMT_1, WHO_AM_I = 0x6B, 0x75
CHIP_ID = 0x68
CLOCK_PLL_GYRO_X = 0x01
DLPF_44HZ = 0x03
BYPASS_EN = 0x02
DATA_RDY = 0x01

#: full scale deg/s -> (FS_SEL, LSB per deg/s)
GYRO_RANGES: dict[int, tuple[int, float]] = {250: (0, 131.0), 500: (1, 65.5), 1000: (2, 32.8), 2000: (3, 16.4)}
#: full scale g -> (AFS_SEL, LSB per g)
ACCEL_RANGES: dict[int, tuple[int, float]] = {2: (0, 16384.0), 4: (1, 8192.0), 8: (2, 4096.0), 16: (3, 2048.0)}
#: output rate Hz -> SMPLRT_DIV (1 kHz / (1 + div), low-pass filter on)
OUTPUT_RATES_HZ: dict[int, int] = {10: 99, 50: 19, 100: 9, 200: 4, 500: 1, 1000: 0}


class MPU6050(AccelGyro):
    """Driver: checks WHO_AM_I, wakes the chip on the gyroscope clock, sets the low-pass filter, rate and full
    scales, turns the auxiliary-bus bypass on and the data-ready flag; ``read()`` gives ``acc_ms2`` and ``gyr_rads``
    when DATA_RDY_INT is set."""

    SPEC = ChipSpec("MPU-6050", DEFAULT_ADDRESS, 100, ACCEL_RANGES, GYRO_RANGES, OUTPUT_RATES_HZ)

    def _configure(self) -> None:
        found = self.device.read_byte(WHO_AM_I)
        if found != CHIP_ID:
            raise SensorError(
                f"no MPU-6050 at {self.device.address:#04x}: WHO_AM_I (0x75) reads {found:#04x}, "
                "expected 0x68 (an MPU-6500 reads 0x70, an MPU-9250 0x71; an ICM-20948 answers 0xea "
                "at register 0x00)"
            )
        self.device.write_byte(PWR_MGMT_1, CLOCK_PLL_GYRO_X)  # out of sleep
        self.device.write_byte(CONFIG, DLPF_44HZ)
        self.device.write_byte(SMPLRT_DIV, self.rate_code)
        self.device.write_byte(GYRO_CONFIG, self.gyro_fs << 3)
        self.device.write_byte(ACCEL_CONFIG, self.accel_fs << 3)
        self.device.write_byte(INT_PIN_CFG, BYPASS_EN)
        self.device.write_byte(INT_ENABLE, DATA_RDY)

    def _read(self) -> Reading:
        if not self.device.read_byte(INT_STATUS) & DATA_RDY:
            return NOT_READY
        counts = words(self.device.read_block(ACCEL_XOUT_H, 14), big_endian=True)  # accel, temperature, gyro
        return self._scaled(counts[:3], counts[4:])


def with_magnetometer(
    magnetometer_class: Callable[..., Sensor],
    bus: I2CBus,
    address: int,
    orientation: Any,
    *,
    acc_address: int = DEFAULT_ADDRESS,
    accel_range_g: int = 4,
    gyro_range_dps: int = 2000,
    rate_hz: int = 100,
    retry: RetryPolicy | None = None,
    sleep: Callable[[float], None] | None = None,
    **magnetometer_options: Any,
) -> NineAxis:
    """An MPU-6050 (set up first: its bypass lets a magnetometer on its auxiliary bus answer) and a magnetometer of
    ``magnetometer_class`` at ``address``, both mapped from a flat, top-up board (module docstring)."""
    inertial = MPU6050(
        bus,
        acc_address,
        orientation,
        accel_range_g=accel_range_g,
        gyro_range_dps=gyro_range_dps,
        rate_hz=rate_hz,
        retry=retry,
        sleep=sleep,
    )
    magnetometer = magnetometer_class(
        bus, address, mounting(orientation, Z_UP_TO_BODY), retry=retry, sleep=sleep, **magnetometer_options
    )
    return NineAxis(magnetometer, inertial)
