"""What every sensor driver shares: the reading, the mounting orientation, I2C access with bounded retries, health.

A driver talks to its chip through an injected ``bus``: any object with the smbus2 ``SMBus`` methods it uses, as the
``I2CBus`` protocol names them (``read_byte_data``, ``write_byte_data``, ``read_i2c_block_data``,
``write_i2c_block_data``). On hardware the service passes ``smbus2.SMBus(1)``; in tests it passes an emulator from
``magnet.emulators``. Nothing here imports smbus2.

Failure policy (chosen once, for every driver):
- An ``OSError`` whose errno is transient (EIO, EREMOTEIO, EBUSY, ETIMEDOUT, EAGAIN) is retried per the device's
  ``magnet.retry.RetryPolicy`` (``TRANSFER_RETRY``: 4 tries, waits of 2, 4, 8 ms; the sleep is injectable), every
  try counted in the device's ``Health`` (``sensor.health``: the first device's); after ``unhealthy_after`` failed
  transfers in a row it reports ``healthy == False``, and the next good transfer makes it healthy again.
- ``read()`` raises ``SensorReadError`` (a ``SensorError``, so an ``OSError``) when the retries are exhausted (or the
  error is not transient). What to do about a failing sensor (wait, back off, report) is the caller's:
  ``magnet.edge.readloop.ReadLoop`` is the one loop that does it, with the same policy type and health record.
- Construction (identity check, configuration) raises ``SensorError`` (an ``OSError``) with a message that says what
  to check, because a sensor that cannot be set up is a configuration problem, not a glitch.
"""

from __future__ import annotations

import dataclasses
import errno
import logging
import time
from collections.abc import Callable
from typing import Any, Protocol, runtime_checkable

import numpy as np

from magnet.frames import orientation_matrix
from magnet.retry import TRANSFER_RETRY, Health, RetryPolicy, cause_of

log = logging.getLogger(__name__)

#: errnos of an I2C transfer worth retrying: bus noise, clock stretching, arbitration loss, a NACK in mid-transfer.
TRANSIENT_ERRNOS = frozenset({errno.EIO, errno.EREMOTEIO, errno.EBUSY, errno.ETIMEDOUT, errno.EAGAIN})


class SensorError(OSError):
    """A sensor cannot be used: wrong chip at the address, no answer after the retries, bad configuration."""


class SensorReadError(SensorError):
    """One ``Sensor.read()`` failed after the driver's retries: the bus or the chip is not answering."""


@runtime_checkable
class I2CBus(Protocol):
    """The smbus2 ``SMBus`` methods the drivers use (``smbus2.SMBus`` and every ``magnet.emulators`` bus satisfy it).

    ``i2c_addr`` is the 7-bit address, ``register`` the chip's sub-address, values are bytes 0..255.
    """

    def read_byte_data(self, i2c_addr: int, register: int, force: Any = None) -> int: ...

    def write_byte_data(self, i2c_addr: int, register: int, value: int, force: Any = None) -> None: ...

    def read_i2c_block_data(self, i2c_addr: int, register: int, length: int, force: Any = None) -> list[int]: ...

    def write_i2c_block_data(self, i2c_addr: int, register: int, data: list[int], force: Any = None) -> None: ...


@dataclasses.dataclass(frozen=True)
class Reading:
    """One sample of a sensor, in the body frame.

    Attributes:
        mag_ut: magnetic field, shape (3,), uT; None when there is no magnetometer, no new data or an overflow.
        acc_ms2: specific force, shape (3,), m/s^2 (a level still device reads about (0, 0, -9.81)); None when there
            is no accelerometer.
        gyr_rads: angular rate, shape (3,), rad/s, body frame (right-handed about x, y, z: a clockwise turn seen from
            above is +z); None when there is no gyroscope.
        overflow: an axis saturated (the value is withheld, never passed on as a field).
        ready: the chip had a new sample (False: nothing new since the last read; no field is given).
        raw: the magnetometer's raw codes in the chip's own axis order x, y, z (shape (3,), int), when read.
    """

    mag_ut: np.ndarray | None = None
    acc_ms2: np.ndarray | None = None
    overflow: bool = False
    ready: bool = True
    raw: np.ndarray | None = None
    gyr_rads: np.ndarray | None = None

    @property
    def ok(self) -> bool:
        """True when the reading carries a usable field, acceleration or angular rate."""
        return (
            self.ready
            and not self.overflow
            and (self.mag_ut is not None or self.acc_ms2 is not None or self.gyr_rads is not None)
        )


NOT_READY = Reading(ready=False)


# --------------------------------------------------------------------------------------------------- retry, health


class I2CDevice:
    """One chip at one I2C address, with every transfer retried per ``retry`` (a ``RetryPolicy`` that gives up) and
    counted in ``health`` (a ``Health``: tries, errors by errno name, retries, healthy)."""

    def __init__(
        self,
        bus: I2CBus,
        address: int,
        *,
        retry: RetryPolicy = TRANSFER_RETRY,
        sleep: Callable[[float], None] = time.sleep,
    ) -> None:
        if not 0x03 <= int(address) <= 0x77:
            raise ValueError(f"I2C address must be in 0x03..0x77, got {address:#x}")
        if retry.give_up_after is None:
            raise ValueError("an I2C transfer's retry policy must give up (give_up_after)")
        self.bus = bus
        self.address = int(address)
        self.retry = retry
        self.sleep = sleep
        self.health = Health()

    def _transfer(self, method: str, *args: Any) -> Any:
        call = getattr(self.bus, method)
        tries = 0
        while True:
            tries += 1
            self.health.attempts += 1
            try:
                result = call(self.address, *args)
            except OSError as exc:
                self._failed(method, exc, tries)
                continue
            self.health.succeeded()
            return result

    def _failed(self, method: str, exc: OSError, tries: int) -> None:
        """Count a failed try; raise ``SensorError`` when it is not worth another, else wait before the next."""
        code = exc.errno or 0
        if self.health.failed(cause_of(exc), f"{method} at {self.address:#04x}: {exc}", self.retry):
            log.warning("I2C device at %#04x unhealthy after %d failed transfers: %s", self.address, tries, exc)
        if code not in TRANSIENT_ERRNOS or self.retry.gives_up(tries):
            raise SensorError(
                code,
                f"I2C {method} at address {self.address:#04x} failed after {tries} attempt(s): {exc.strerror or exc}",
            ) from exc
        self.health.retries += 1
        delay = self.retry.delay_s(tries)
        self.sleep(delay)
        self.health.waited_s += delay

    def read_byte(self, register: int) -> int:
        return int(self._transfer("read_byte_data", register))

    def write_byte(self, register: int, value: int) -> None:
        self._transfer("write_byte_data", register, value & 0xFF)

    def read_block(self, register: int, length: int) -> list[int]:
        data = list(self._transfer("read_i2c_block_data", register, length))
        if len(data) != length:
            raise SensorError(errno.EIO, f"short read at {self.address:#04x}: {len(data)} of {length} bytes")
        return data

    def write_block(self, register: int, values: list[int]) -> None:
        self._transfer("write_i2c_block_data", register, [v & 0xFF for v in values])


def to_signed(value: int, bits: int = 16) -> int:
    """Two's complement of an unsigned ``bits``-bit integer."""
    value &= (1 << bits) - 1
    return value - (1 << bits) if value & (1 << (bits - 1)) else value


class Sensor:
    """Base of every driver: ``read()`` wraps the chip-specific ``_read()`` in the failure policy above.

    Subclasses set ``self.device`` (an ``I2CDevice``) or ``self.devices``, and implement ``_read() -> Reading``
    in the chip's axes; the base rotates ``mag_ut``, ``acc_ms2`` and ``gyr_rads`` into the body frame with
    ``self.rotation``.
    """

    rotation: np.ndarray = np.eye(3)
    devices: tuple[I2CDevice, ...] = ()

    def _attach(
        self,
        bus: I2CBus,
        address: int,
        orientation: Any,
        retry: RetryPolicy | None,
        sleep: Callable[[float], None] | None,
    ) -> I2CDevice:
        """Set ``self.device`` (the chip at ``address`` on ``bus``, with the retry policy), ``self.devices`` and the
        mounting ``self.rotation``; returns the device."""
        self.device = I2CDevice(
            bus, address, retry=TRANSFER_RETRY if retry is None else retry, sleep=time.sleep if sleep is None else sleep
        )
        self.devices = (self.device,)
        self.rotation = orientation_matrix(orientation)
        return self.device

    def _read(self) -> Reading:  # pragma: no cover - abstract
        raise NotImplementedError

    @property
    def health(self) -> Health:
        return self.devices[0].health

    def read(self) -> Reading:
        """One sample in the body frame; ``SensorReadError`` when the bus failed after the retries (counted in each
        device's ``health``; what to do next is the read loop's, ``magnet.edge.readloop``)."""
        try:
            reading = self._read()
        except SensorError as exc:
            raise SensorReadError(
                exc.errno or errno.EIO, f"{type(self).__name__} read failed: {exc.strerror or exc}"
            ) from exc
        return self._to_body(reading)

    def _to_body(self, reading: Reading) -> Reading:
        def rotate(vector: np.ndarray | None) -> np.ndarray | None:
            return None if vector is None else self.rotation @ vector

        return dataclasses.replace(
            reading, mag_ut=rotate(reading.mag_ut), acc_ms2=rotate(reading.acc_ms2), gyr_rads=rotate(reading.gyr_rads)
        )


class Combined(Sensor):
    """A magnetometer and an accelerometer read together as one sensor (e.g. AK09918C + BMA456).

    ``read()`` reads the magnetometer, then the accelerometer, and merges them: field and flags from the
    magnetometer, ``acc_ms2`` (and ``gyr_rads``) from the accelerometer. Either part failing raises its
    ``SensorReadError``. Each part keeps its own orientation.
    """

    def __init__(self, magnetometer: Sensor, accelerometer: Sensor) -> None:
        self.magnetometer = magnetometer
        self.accelerometer = accelerometer
        self.devices = (*magnetometer.devices, *accelerometer.devices)

    @property
    def health(self) -> Health:
        return self.magnetometer.health

    def read(self) -> Reading:
        mag = self.magnetometer.read()
        acc = self.accelerometer.read()
        return dataclasses.replace(mag, acc_ms2=acc.acc_ms2, gyr_rads=acc.gyr_rads)
