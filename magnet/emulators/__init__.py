"""Register-level emulators of the supported chips (see ``magnet.emulators.base`` for what they share).

``magnet.emulators.<chip>.<CHIP>Emulator(source=None, ...)`` implements the smbus2 ``SMBus`` methods on a register
map that behaves as the chip's datasheet says; ``source.measure() -> (mag_ut (3,), acc_ms2 (3,))`` gives the true
field and specific force in the body frame, and ``source.measure_imu()`` (when there) adds the angular rate gyr_rads.
"""

from collections.abc import Callable
from typing import Any

from magnet.emulators.base import ConstantSource, EmulatedBus, FaultInjector, SourceTap

__all__ = ["ConstantSource", "EmulatedBus", "FaultInjector", "SourceTap"]


def emulator_for(name: str, source: Any = None, **options: Any) -> Any:
    """The emulated bus for sensor ``name`` (as in ``magnet.drivers.SENSORS``), fed by ``source``.

    For the packages and pairs (``ak09918c+bma456``, ``lsm303dlh``, ``icm20948``, ``lsm9ds1``, ``mpu6050+...``) the
    bus holds every chip, sharing the source (a source with ``measure_imu`` also gives the gyroscopes their rate).
    ``options`` go to the magnetometer's emulator (``gain_error``, ``temperature_c``, ``tempco_per_k``) or the whole
    bus (``rotation``, ``clock``, ``faults``, ``acc_address``).
    """
    from magnet.emulators import ak09918c, hmc5883l, icm20948, lsm9ds1, lsm303dlh, mpu6050, qmc5883l

    table: dict[str, Callable[..., Any]] = {
        "hmc5883l": hmc5883l.HMC5883LEmulator,
        "qmc5883l": qmc5883l.QMC5883LEmulator,
        "lsm303dlh": lsm303dlh.LSM303DLHEmulator,
        "ak09918c+bma456": ak09918c.ak09918c_bma456_bus,
        "icm20948": icm20948.ICM20948Emulator,
        "lsm9ds1": lsm9ds1.LSM9DS1Emulator,
        "mpu6050+hmc5883l": mpu6050.mpu6050_with(hmc5883l.HMC5883LEmulator),
        "mpu6050+qmc5883l": mpu6050.mpu6050_with(qmc5883l.QMC5883LEmulator),
    }
    try:
        factory = table[name.strip().lower()]
    except KeyError:
        raise ValueError(f"no emulator for sensor {name!r}: use one of {', '.join(table)}") from None
    return factory(source, **options)


__all__.append("emulator_for")
