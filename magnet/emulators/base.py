"""Register-level chip emulators: what they share.

An emulator is an I2C device with a 256-byte register map and an address pointer. It implements the smbus2
``SMBus`` methods drivers use (``read_byte_data``, ``write_byte_data``, ``read_i2c_block_data``,
``write_i2c_block_data``, ``read_byte``, ``write_byte``, ``read_word_data``, ``write_word_data``, ``close``), so a
driver cannot tell it from ``smbus2.SMBus(1)`` with the chip on it. Several emulators share one bus through
``EmulatedBus``; a single emulator is also a bus by itself (it answers only its own addresses; any other address
gets EREMOTEIO, as a NACK does on a Raspberry Pi).

Behaviour follows the datasheets, written independently of the drivers. Time: with ``clock=None`` a chip in
continuous mode has a new measurement ready as soon as the previous one has been read (no waiting, for fast tests
and ``magnet sample --emulate``); with ``clock`` (a callable returning seconds) measurements complete at the chip's
output data rate, so "not ready" and data overrun can be exercised.

The true field comes from a ``source`` with ``.measure() -> (mag_ut (3,), acc_ms2 (3,))`` in the body frame (the
simulator's ``SensorStream``); ``ConstantSource`` is the stand-in. ``rotation`` (3x3) maps body to chip axes
(chip = rotation @ body); identity means the chip's marked axes are the body axes.
"""

from __future__ import annotations

import errno
import os
from collections.abc import Callable, Iterable, Mapping
from typing import Any

import numpy as np
import numpy.typing as npt

STANDARD_GRAVITY_MS2 = 9.80665


class ConstantSource:
    """A device in a constant field, specific force and angular rate (default: still and level): ``measure()``
    always returns the same (mag_ut, acc_ms2), ``measure_imu()`` the same (mag_ut, acc_ms2, gyr_rads)."""

    def __init__(
        self,
        mag_ut: npt.ArrayLike = (20.0, 0.0, 45.0),
        acc_ms2: npt.ArrayLike = (0.0, 0.0, -STANDARD_GRAVITY_MS2),
        gyr_rads: npt.ArrayLike = (0.0, 0.0, 0.0),
    ) -> None:
        self.mag_ut = np.asarray(mag_ut, dtype=float)
        self.acc_ms2 = np.asarray(acc_ms2, dtype=float)
        self.gyr_rads = np.asarray(gyr_rads, dtype=float)
        self.count = 0

    def measure(self) -> tuple[np.ndarray, np.ndarray]:
        self.count += 1
        return self.mag_ut.copy(), self.acc_ms2.copy()

    def measure_imu(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        mag, acc = self.measure()
        return mag, acc, self.gyr_rads.copy()


class SourceTap:
    """Shares one source between the chips of a package (magnetometer + accelerometer) so both see one sample.

    ``mag()`` draws a new sample from the source; ``acc()`` and ``gyr()`` return the accelerometer and gyroscope
    parts of the latest sample (drawing one if there is none yet). The magnetometer is the pace-setter, as in
    ``magnet sample``. A source with ``measure_imu() -> (mag, acc, gyr)`` gives the angular rate; one with only
    ``measure()`` is still (zero rate).
    """

    def __init__(self, source: Any) -> None:
        self.source = source if source is not None else ConstantSource()
        self._latest: tuple[np.ndarray, ...] | None = None

        self._unused_by_mag = False  # the accelerometer drew the latest sample first: the magnetometer gets it too

    def _draw(self) -> tuple[np.ndarray, ...]:
        imu = getattr(self.source, "measure_imu", None)
        sample = imu() if imu is not None else (*self.source.measure(), np.zeros(3))
        self._latest = latest = tuple(np.asarray(v, dtype=float) for v in sample)
        return latest

    def mag(self) -> np.ndarray:
        latest = self._latest if self._unused_by_mag and self._latest is not None else self._draw()
        self._unused_by_mag = False
        return latest[0]

    def acc(self) -> np.ndarray:
        return self._part(1)

    def gyr(self) -> np.ndarray:
        return self._part(2)

    def _part(self, index: int) -> np.ndarray:
        latest = self._latest
        if latest is None:
            latest = self._draw()
            self._unused_by_mag = True
        return latest[index]


class FaultInjector:
    """Makes bus transactions fail with an ``OSError`` of a chosen errno.

    ``schedule``: a mapping {transaction index: errno} or a sequence with an errno (or 0/None for success) per
    transaction, counted from 0 on this injector. ``probability``: chance per transaction (after the schedule),
    drawing the errno from ``errnos`` with a seeded generator. ``injected`` counts the failures raised.
    """

    def __init__(
        self,
        schedule: Mapping[int, int] | Iterable[int | None] = (),
        probability: float = 0.0,
        errnos: Iterable[int] = (errno.EIO,),
        seed: int = 0,
    ) -> None:
        if not 0.0 <= probability <= 1.0:
            raise ValueError(f"fault probability must be within 0..1, got {probability}")
        self.schedule = dict(schedule) if isinstance(schedule, Mapping) else dict(enumerate(schedule))
        self.probability = probability
        self.errnos = tuple(errnos)
        self.rng = np.random.default_rng(seed)
        self.transactions = 0
        self.injected = 0

    def check(self) -> None:
        index = self.transactions
        self.transactions += 1
        code = self.schedule.get(index)
        if not code and self.probability and self.rng.random() < self.probability:
            code = self.errnos[int(self.rng.integers(len(self.errnos)))]
        if code:
            self.injected += 1
            raise OSError(code, os.strerror(code))


def _nack(address: int) -> OSError:
    return OSError(errno.EREMOTEIO, f"{os.strerror(errno.EREMOTEIO)} (no device at {address:#04x})")


class RegisterDevice:
    """One emulated chip: register map, address pointer, transactions. Subclasses add the chip's behaviour through
    ``_update()`` (called at the start of every transaction: measurements due), ``_on_read(register)``,
    ``_on_write(register, value)``, ``_after_read(registers)`` and ``_next_pointer(register)``."""

    addresses: tuple[int, ...] = ()
    read_only: frozenset[int] = frozenset()

    def __init__(self, *, clock: Callable[[], float] | None = None, faults: FaultInjector | None = None) -> None:
        self.regs = bytearray(256)
        self.pointer = 0
        self.clock = clock
        self.faults = faults
        self.transactions = 0
        self.closed = False

    # ---- behaviour hooks
    def _update(self) -> None:
        """Complete any measurement that is due (the chip's own timing)."""

    def _on_read(self, register: int) -> int:
        return self.regs[register]

    def _on_write(self, register: int, value: int) -> None:
        if register not in self.read_only:
            self.regs[register] = value

    def _after_read(self, registers: list[int]) -> None:
        """Side effects of one read transaction (status bits, locks) once all its bytes went out."""

    def _next_pointer(self, register: int) -> int:
        return (register + 1) & 0xFF

    def _translate(self, register: int) -> tuple[int, bool]:
        """(start register, auto-increment?) for a sub-address as sent on the bus."""
        return register & 0xFF, True

    # ---- transactions
    def _begin(self, address: int) -> None:
        if address not in self.addresses:
            raise _nack(address)
        if self.closed:
            raise OSError(errno.EBADF, "bus closed")
        if self.faults is not None:
            self.faults.check()
        self.transactions += 1
        self._update()

    def _read(self, address: int, register: int | None, length: int) -> list[int]:
        self._begin(address)
        if register is not None:
            self.pointer, increment = self._translate(register)
        else:
            increment = True
        out, touched = [], []
        for _ in range(length):
            touched.append(self.pointer)
            out.append(self._on_read(self.pointer) & 0xFF)
            if increment:
                self.pointer = self._next_pointer(self.pointer)
        self._after_read(touched)
        return out

    def _write(self, address: int, register: int, values: list[int]) -> None:
        self._begin(address)
        self.pointer, increment = self._translate(register)
        for value in values:
            if not 0 <= int(value) <= 0xFF:
                raise ValueError(f"byte out of range: {value}")
            self._on_write(self.pointer, int(value))
            if increment:
                self.pointer = self._next_pointer(self.pointer)

    # ---- the smbus2 SMBus methods
    def read_byte_data(self, i2c_addr: int, register: int, force: Any = None) -> int:
        return self._read(i2c_addr, register, 1)[0]

    def write_byte_data(self, i2c_addr: int, register: int, value: int, force: Any = None) -> None:
        self._write(i2c_addr, register, [value])

    def read_i2c_block_data(self, i2c_addr: int, register: int, length: int, force: Any = None) -> list[int]:
        if not 1 <= length <= 32:
            raise ValueError(f"block length must be 1..32, got {length}")  # smbus2 does the same
        return self._read(i2c_addr, register, length)

    def write_i2c_block_data(self, i2c_addr: int, register: int, data: list[int], force: Any = None) -> None:
        self._write(i2c_addr, register, list(data))

    def read_byte(self, i2c_addr: int, force: Any = None) -> int:
        return self._read(i2c_addr, None, 1)[0]

    def write_byte(self, i2c_addr: int, value: int, force: Any = None) -> None:
        self._begin(i2c_addr)
        self.pointer = self._translate(value)[0]

    def read_word_data(self, i2c_addr: int, register: int, force: Any = None) -> int:
        low, high = self._read(i2c_addr, register, 2)
        return low | (high << 8)

    def write_word_data(self, i2c_addr: int, register: int, value: int, force: Any = None) -> None:
        self._write(i2c_addr, register, [value & 0xFF, (value >> 8) & 0xFF])

    def close(self) -> None:
        self.closed = True

    def __enter__(self) -> RegisterDevice:
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()

    # ---- helpers for subclasses
    def now(self) -> float | None:
        return None if self.clock is None else float(self.clock())


class EmulatedBus:
    """Several emulated chips on one bus, dispatched by address (the smbus2 methods, like ``SMBus``)."""

    def __init__(self, *devices: RegisterDevice, faults: FaultInjector | None = None) -> None:
        self.devices: dict[int, RegisterDevice] = {}
        for device in devices:
            for address in device.addresses:
                if address in self.devices:
                    raise ValueError(f"two emulated devices answer at {address:#04x}")
                self.devices[address] = device
        self.faults = faults

    def _device(self, address: int) -> RegisterDevice:
        if self.faults is not None:
            self.faults.check()
        try:
            return self.devices[address]
        except KeyError:
            raise _nack(address) from None

    def __getattr__(self, method: str) -> Callable[..., Any]:
        if method not in _SMBUS_METHODS:
            raise AttributeError(method)
        return lambda address, *args, **kw: getattr(self._device(address), method)(address, *args, **kw)

    def close(self) -> None:
        for device in self.devices.values():
            device.close()


_SMBUS_METHODS = frozenset(
    {
        "read_byte_data",
        "write_byte_data",
        "read_i2c_block_data",
        "write_i2c_block_data",
        "read_byte",
        "write_byte",
        "read_word_data",
        "write_word_data",
    }
)


def sensitivity_factor(
    gain_error: Any, temperature_c: float, tempco_per_k: float, reference_c: float = 25.0
) -> np.ndarray:
    """Per-axis sensitivity multiplier (3,): (1 + gain_error) * (1 + tempco_per_k * (temperature_c - reference_c))."""
    error = np.broadcast_to(np.asarray(gain_error, dtype=float), (3,))
    return (1.0 + error) * (1.0 + tempco_per_k * (temperature_c - reference_c))


class SensorDevice(RegisterDevice):
    """A chip that senses the source: ``address`` overrides the chip's own, ``tap`` shares one source sample between
    the chips of one package, ``rotation`` (3x3) maps body to chip axes (identity: the marked axes are the body's)."""

    def __init__(
        self,
        source: Any = None,
        *,
        address: int | None = None,
        rotation: Any = None,
        clock: Callable[[], float] | None = None,
        faults: FaultInjector | None = None,
        tap: SourceTap | None = None,
    ) -> None:
        super().__init__(clock=clock, faults=faults)
        if address is not None:
            self.addresses = (address,)
        self.tap = tap or SourceTap(source)
        self.rotation = np.eye(3) if rotation is None else np.asarray(rotation, dtype=float)
        self.unread = False  # a measurement placed and not yet read
        self.next_due: float | None = None  # clock time of the next continuous measurement

    def _power_on_reset(self, power_on: dict[int, int]) -> None:
        """Registers to their power-on values (``power_on``: register -> value, 0 elsewhere); no data pending."""
        self.regs[:] = bytes(256)
        for register, value in power_on.items():
            self.regs[register] = value
        self.unread = False
        self.next_due = None

    def _measure(self) -> None:
        """Take one measurement from the source into the data registers."""
        raise NotImplementedError

    def _measure_continuously(self, period_s: float, may_measure: bool = True) -> None:
        """Continuous mode. With no clock: a new measurement as soon as the last one was read (when
        ``may_measure``). With a clock: one every ``period_s`` seconds from the first call, several at once when
        reads fell behind (the chip overwrites unread data)."""
        now = self.now()
        if now is None:
            if not self.unread and may_measure:
                self._measure()
            return
        if self.next_due is None:
            self.next_due = now + period_s
        while now >= self.next_due:
            self._measure()
            self.next_due += period_s


class MagnetometerDevice(SensorDevice):
    """A magnetometer chip: adds a per-axis ``gain_error`` and a gain drift of ``tempco_per_k`` per kelvin away from
    25 deg C at ``temperature_c`` (``sensitivity()``, see ``sensitivity_factor``)."""

    def __init__(
        self,
        source: Any = None,
        *,
        gain_error: Any = (0.0, 0.0, 0.0),
        temperature_c: float = 25.0,
        tempco_per_k: float = 0.0,
        **common: Any,
    ) -> None:
        super().__init__(source, **common)
        self.gain_error = np.asarray(gain_error, dtype=float)
        self.temperature_c = temperature_c
        self.tempco_per_k = tempco_per_k

    def sensitivity(self) -> np.ndarray:
        """Per-axis sensitivity multiplier (3,) now."""
        return sensitivity_factor(self.gain_error, self.temperature_c, self.tempco_per_k)


def to_bytes(value: int, bits: int = 16) -> tuple[int, int]:
    """(high byte, low byte) of a two's complement value."""
    raw = int(value) & ((1 << bits) - 1)
    return (raw >> 8) & 0xFF, raw & 0xFF
