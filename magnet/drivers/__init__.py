"""Sensor drivers over an injected smbus2-style bus, and ``open_sensor`` by name.

``magnet.drivers.<chip>.<CHIP>(bus, address=DEFAULT, orientation=None)`` with ``.read() -> Reading`` (see
``magnet.drivers.base`` for the reading, retries and health, ``magnet.frames`` for orientation names). Nothing
here imports smbus2: the service opens ``smbus2.SMBus(n)`` and passes it in, or passes an emulator from
``magnet.emulators``.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

from magnet.drivers.base import Combined, I2CBus, Reading, Sensor, SensorError, SensorReadError
from magnet.retry import Health, RetryPolicy

__all__ = [
    "GYROSCOPES",
    "SENSORS",
    "Combined",
    "Health",
    "I2CBus",
    "Reading",
    "RetryPolicy",
    "Sensor",
    "SensorError",
    "SensorReadError",
    "has_accelerometer",
    "has_gyroscope",
    "open_sensor",
]


def _hmc5883l(bus: I2CBus, address: int | None, orientation: Any, **kw: Any) -> Sensor:
    from magnet.drivers.hmc5883l import DEFAULT_ADDRESS, HMC5883L

    return HMC5883L(bus, address or DEFAULT_ADDRESS, orientation, **kw)


def _qmc5883l(bus: I2CBus, address: int | None, orientation: Any, **kw: Any) -> Sensor:
    from magnet.drivers.qmc5883l import DEFAULT_ADDRESS, QMC5883L

    return QMC5883L(bus, address or DEFAULT_ADDRESS, orientation, **kw)


def _lsm303dlh(bus: I2CBus, address: int | None, orientation: Any, **kw: Any) -> Sensor:
    from magnet.drivers.lsm303dlh import DEFAULT_ADDRESS, LSM303DLH

    return LSM303DLH(bus, address or DEFAULT_ADDRESS, orientation, **kw)


def _ak09918c_bma456(
    bus: I2CBus, address: int | None, orientation: Any, *, acc_address: int | None = None, **kw: Any
) -> Sensor:
    from magnet.drivers import ak09918c, bma456

    return Combined(
        ak09918c.AK09918C(bus, address or ak09918c.DEFAULT_ADDRESS, orientation, **kw),
        bma456.BMA456(bus, acc_address or bma456.DEFAULT_ADDRESS, orientation, **kw),
    )


def _icm20948(bus: I2CBus, address: int | None, orientation: Any, **kw: Any) -> Sensor:
    from magnet.drivers.icm20948 import ICM20948, MAG_ADDRESS

    return ICM20948(bus, address or MAG_ADDRESS, orientation, **kw)


def _lsm9ds1(bus: I2CBus, address: int | None, orientation: Any, **kw: Any) -> Sensor:
    from magnet.drivers.lsm9ds1 import DEFAULT_ADDRESS, LSM9DS1

    return LSM9DS1(bus, address or DEFAULT_ADDRESS, orientation, **kw)


def _mpu6050_with(magnetometer: str) -> Callable[..., Sensor]:
    def factory(
        bus: I2CBus, address: int | None, orientation: Any, *, acc_address: int | None = None, **kw: Any
    ) -> Sensor:
        from magnet.drivers import hmc5883l, mpu6050, qmc5883l

        chip = {
            "hmc5883l": (hmc5883l.HMC5883L, hmc5883l.DEFAULT_ADDRESS),
            "qmc5883l": (qmc5883l.QMC5883L, qmc5883l.DEFAULT_ADDRESS),
        }[magnetometer]
        return mpu6050.with_magnetometer(
            chip[0], bus, address or chip[1], orientation, acc_address=acc_address or mpu6050.DEFAULT_ADDRESS, **kw
        )

    return factory


#: sensor name -> (factory(bus, address, orientation, **options), has an accelerometer, one-line description)
SENSORS: dict[str, tuple[Callable[..., Sensor], bool, str]] = {
    "hmc5883l": (_hmc5883l, False, "Honeywell HMC5883L magnetometer at 0x1E"),
    "qmc5883l": (_qmc5883l, False, "QST QMC5883L magnetometer at 0x0D"),
    "lsm303dlh": (_lsm303dlh, True, "ST LSM303DLH magnetometer 0x1E + accelerometer 0x18"),
    "ak09918c+bma456": (_ak09918c_bma456, True, "AKM AK09918C magnetometer 0x0C + Bosch BMA456 accelerometer 0x18"),
    "icm20948": (
        _icm20948,
        True,
        "TDK InvenSense ICM-20948 accelerometer + gyroscope 0x68 + AK09916 magnetometer 0x0C",
    ),
    "lsm9ds1": (_lsm9ds1, True, "ST LSM9DS1 accelerometer + gyroscope 0x6B + magnetometer 0x1E"),
    "mpu6050+hmc5883l": (
        _mpu6050_with("hmc5883l"),
        True,
        "InvenSense MPU-6050 accelerometer + gyroscope 0x68 + Honeywell HMC5883L magnetometer 0x1E",
    ),
    "mpu6050+qmc5883l": (
        _mpu6050_with("qmc5883l"),
        True,
        "InvenSense MPU-6050 accelerometer + gyroscope 0x68 + QST QMC5883L magnetometer 0x0D",
    ),
}
#: the sensors with a gyroscope (``Reading.gyr_rads``)
GYROSCOPES = frozenset({"icm20948", "lsm9ds1", "mpu6050+hmc5883l", "mpu6050+qmc5883l"})


def open_sensor(name: str, bus: I2CBus, address: int | None = None, orientation: Any = None, **options: Any) -> Sensor:
    """The driver for sensor ``name`` on ``bus`` (address None = the chip's default; for a pair, the magnetometer's;
    ``acc_address=`` moves the accelerometer). ``options`` go to the driver (``retry``, ``sleep``, settings)."""
    try:
        factory = SENSORS[name.strip().lower()][0]
    except KeyError:
        raise ValueError(f"unknown sensor {name!r}: use one of {', '.join(SENSORS)}") from None
    return factory(bus, address, orientation, **options)


def has_accelerometer(name: str) -> bool:
    return SENSORS[name.strip().lower()][1]


def has_gyroscope(name: str) -> bool:
    return name.strip().lower() in GYROSCOPES
