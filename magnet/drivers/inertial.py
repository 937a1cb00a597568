"""What the accelerometer + gyroscope drivers share: the package frame, setting tables, data words, and the
nine-axis combination of a magnetometer with an accelerometer + gyroscope.

Frames. The InvenSense and ST inertial chips mark their axes right-handed with z up out of the package top (a chip
lying flat, top up, reads +1 g on z). The drivers map that to the body frame (x forward, y right, z down) for a
package lying flat, top up, with its x mark forward: body = (x, -y, -z), ``Z_UP_TO_BODY``. A magnetometer in the same
package has its own axes (see each chip); the driver maps it to the same body frame, so a package read with the
default orientation gives field, specific force and rate in one frame. ``orientation`` (as for every driver, see
``magnet.frames.orientation_matrix``) then turns the package in the body: body = orientation @ package frame.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable, Mapping
from typing import Any, ClassVar, TypedDict

import numpy as np

from magnet.drivers.base import Combined, I2CBus, Reading, Sensor, to_signed
from magnet.frames import orientation_matrix
from magnet.retry import RetryPolicy
from magnet.units import STANDARD_GRAVITY_MS2

#: chip axes with z up out of the package -> body axes of a package lying flat, top up, x forward
Z_UP_TO_BODY = np.diag([1.0, -1.0, -1.0])
RAD_PER_DEG = math.pi / 180.0
INT16_LIMITS = (-32768, 32767)


def mounting(orientation: Any, chip_to_package: np.ndarray) -> np.ndarray:
    """Chip axes -> body: ``orientation_matrix(orientation) @ chip_to_package`` (3, 3)."""
    return orientation_matrix(orientation) @ chip_to_package


def choose(value: Any, table: Mapping[Any, Any], what: str, chip: str) -> Any:
    """``table[value]``, or ValueError naming the chip, the setting and the values allowed."""
    try:
        return table[value]
    except (KeyError, TypeError):
        raise ValueError(
            f"{chip} {what} must be one of {', '.join(f'{k:g}' for k in sorted(table))}, got {value!r}"
        ) from None


def words(block: list[int], big_endian: bool) -> np.ndarray:
    """Signed 16-bit words (len(block) // 2,) from bytes, high byte first when ``big_endian``."""
    pairs = [(block[i], block[i + 1]) for i in range(0, len(block) - 1, 2)]
    return np.array([to_signed((a << 8) | b if big_endian else (b << 8) | a) for a, b in pairs])


def saturated(counts: np.ndarray) -> bool:
    """A 16-bit channel at either end of its range: the quantity is beyond the full scale."""
    return bool(np.any((counts <= INT16_LIMITS[0]) | (counts >= INT16_LIMITS[1])))


@dataclasses.dataclass(frozen=True)
class ChipSpec:
    """What an accelerometer + gyroscope chip offers: ``chip`` (its name in messages), ``default_address`` (7-bit
    I2C), ``default_rate_hz``, ``accel_ranges`` (full scale g -> (register code, scale)), ``gyro_ranges`` (full scale
    deg/s -> (register code, scale)) and ``output_rates_hz`` (Hz -> register value). The scales are LSB per g and per
    deg/s, or with ``milli_per_lsb`` mg and mdps per LSB (as ST's datasheets give them)."""

    chip: str
    default_address: int
    default_rate_hz: float
    accel_ranges: Mapping[int, tuple[int, float]]
    gyro_ranges: Mapping[int, tuple[int, float]]
    output_rates_hz: Mapping[Any, int]
    milli_per_lsb: bool = False


class AccelGyro(Sensor):
    """Base of the accelerometer + gyroscope drivers: the settings chosen from the chip's tables, the z-up package
    frame, and counts scaled to m/s^2 and rad/s.

    A chip sets ``SPEC`` (its ``ChipSpec``: name, address, rate and the tables of its settings) and implements
    ``_configure``.
    """

    SPEC: ClassVar[ChipSpec]

    def __init__(
        self,
        bus: I2CBus,
        address: int | None = None,
        orientation: Any = None,
        *,
        accel_range_g: int = 4,
        gyro_range_dps: int = 2000,
        rate_hz: float | None = None,
        retry: RetryPolicy | None = None,
        sleep: Callable[[float], None] | None = None,
    ) -> None:
        """Choose the full scales and the output rate from the chip's tables (ValueError naming the chip and the
        values allowed; ``rate_hz`` None: the spec's default rate), attach the chip at ``address`` (None:
        the spec's address) in the package frame, then ``_configure`` it (``rate_code``: the rate's register value)."""
        spec = self.SPEC
        self.accel_fs, accel_scale = choose(accel_range_g, spec.accel_ranges, "accelerometer range (g)", spec.chip)
        self.gyro_fs, gyro_scale = choose(gyro_range_dps, spec.gyro_ranges, "gyroscope range (deg/s)", spec.chip)
        rate = spec.default_rate_hz if rate_hz is None else rate_hz
        self.rate_code: int = choose(rate, spec.output_rates_hz, "output rate (Hz)", spec.chip)
        if spec.milli_per_lsb:
            g_per_lsb, dps_per_lsb = accel_scale / 1000.0, gyro_scale / 1000.0
        else:
            g_per_lsb, dps_per_lsb = 1.0 / accel_scale, 1.0 / gyro_scale
        self.acc_ms2_per_lsb = g_per_lsb * STANDARD_GRAVITY_MS2
        self.gyr_rads_per_lsb = dps_per_lsb * RAD_PER_DEG
        self._attach(bus, spec.default_address if address is None else address, orientation, retry, sleep)
        self.rotation = mounting(orientation, Z_UP_TO_BODY)
        self._configure()

    def _configure(self) -> None:  # pragma: no cover - abstract
        """Check the chip's identity (SensorError naming what answered) and write its settings."""
        raise NotImplementedError

    def _scaled(self, accel: np.ndarray, gyro: np.ndarray) -> Reading:
        """The reading of accelerometer and gyroscope counts (3,) each in the chip's axes; overflow when either is at
        the end of its range."""
        if saturated(accel) or saturated(gyro):
            return Reading(overflow=True)
        return Reading(acc_ms2=accel * self.acc_ms2_per_lsb, gyr_rads=gyro * self.gyr_rads_per_lsb)


class InertialOptions(TypedDict, total=False):
    """What a nine-axis package passes on to its accelerometer + gyroscope (``AccelGyro``'s options; each absent one
    keeps the chip's default: 4 g, 2000 deg/s, the spec's rate)."""

    accel_range_g: int
    gyro_range_dps: int
    rate_hz: float


class NineAxis(Combined):
    """A magnetometer with an accelerometer + gyroscope: the magnetometer sets the pace (a reading is ready when it
    has a new field), the inertial chip gives its latest sample. When the inertial chip has nothing new yet (it runs
    slower than it is polled) its previous sample is held; when it saturated, ``acc_ms2`` and ``gyr_rads`` are None
    for that reading (a saturated rate is never passed on)."""

    def __init__(self, magnetometer: Sensor, inertial: Sensor) -> None:
        super().__init__(magnetometer, inertial)
        self._last: Reading | None = None

    def read(self) -> Reading:
        mag = self.magnetometer.read()
        imu = self.accelerometer.read()
        if imu.ready:
            self._last = imu
        held = self._last
        if held is None or held.overflow:
            return dataclasses.replace(mag, acc_ms2=None, gyr_rads=None)
        return dataclasses.replace(mag, acc_ms2=held.acc_ms2, gyr_rads=held.gyr_rads)
