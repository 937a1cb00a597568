"""Honeywell HMC5883L three-axis magnetometer (I2C address 0x1E).

Registers (datasheet):
- 0x00 Config A: bits 6:5 samples averaged (1, 2, 4, 8), bits 4:2 output rate (0.75, 1.5, 3, 7.5, 15, 30, 75 Hz),
  bits 1:0 measurement mode (normal, positive bias, negative bias).
- 0x01 Config B: bits 7:5 gain GN 0..7, LSB per gauss 1370, 1090, 820, 660, 440, 390, 330, 230.
- 0x02 Mode: bits 1:0 continuous (0), single (1), idle (2, 3).
- 0x03..0x08 data X, Z, Y, each big-endian 12-bit two's complement (-2048..2047); -4096 = overflow.
- 0x09 Status: bit 1 LOCK, bit 0 RDY.  0x0A..0x0C identification 'H', '4', '3'.

field_ut[axis] = counts[axis] / LSB_PER_GAUSS[GN] * 100 * axis_scale[axis]  (axis_scale from the self-test, or 1).
"""

from __future__ import annotations

import dataclasses
import enum
from collections.abc import Callable
from typing import Any

import numpy as np

from magnet.drivers.base import NOT_READY, I2CBus, Reading, Sensor, SensorError, to_signed
from magnet.drivers.selftest import LSB_PER_GAUSS, SelfTestResult, evaluate  # GN -> LSB per gauss (Config B)
from magnet.retry import RetryPolicy

DEFAULT_ADDRESS = 0x1E
IDENTITY = b"H43"

REG_CONFIG_A, REG_CONFIG_B, REG_MODE, REG_DATA, REG_STATUS, REG_ID = 0x00, 0x01, 0x02, 0x03, 0x09, 0x0A
STATUS_RDY, STATUS_LOCK = 0x01, 0x02
OVERFLOW = -4096

#: averaging bits -> samples averaged
AVERAGING: tuple[int, ...] = (1, 2, 4, 8)
#: rate bits -> output rate in Hz (7 is reserved)
OUTPUT_RATE_HZ: tuple[float, ...] = (0.75, 1.5, 3.0, 7.5, 15.0, 30.0, 75.0)
#: the chip's data order in registers 0x03..0x08 -> index into (x, y, z)
REGISTER_AXES: tuple[int, ...] = (0, 2, 1)


class Bias(enum.IntEnum):
    NORMAL = 0
    POSITIVE = 1
    NEGATIVE = 2


class Mode(enum.IntEnum):
    CONTINUOUS = 0
    SINGLE = 1
    IDLE = 2


@dataclasses.dataclass(frozen=True)
class HMC5883LSettings:
    """Measurement configuration: samples averaged (1/2/4/8), output rate in Hz, bias, gain GN (0..7), mode."""

    averaging: int = 8
    rate_hz: float = 75.0
    bias: Bias = Bias.NORMAL
    gain: int = 1
    mode: Mode = Mode.CONTINUOUS

    def __post_init__(self) -> None:
        if self.averaging not in AVERAGING:
            raise ValueError(f"HMC5883L averaging must be one of {AVERAGING}, got {self.averaging}")
        if self.rate_hz not in OUTPUT_RATE_HZ:
            raise ValueError(f"HMC5883L output rate must be one of {OUTPUT_RATE_HZ} Hz, got {self.rate_hz}")
        if not 0 <= self.gain <= 7:
            raise ValueError(f"HMC5883L gain GN must be 0..7, got {self.gain}")

    @property
    def config_a(self) -> int:
        return (AVERAGING.index(self.averaging) << 5) | (OUTPUT_RATE_HZ.index(self.rate_hz) << 2) | int(self.bias)

    @property
    def config_b(self) -> int:
        return self.gain << 5

    @classmethod
    def from_registers(cls, config_a: int, config_b: int, mode: int) -> HMC5883LSettings:
        rate_bits = (config_a >> 2) & 0x7
        bias_bits = config_a & 0x3
        return cls(
            averaging=AVERAGING[(config_a >> 5) & 0x3],
            rate_hz=OUTPUT_RATE_HZ[min(rate_bits, 6)],
            bias=Bias(bias_bits if bias_bits < 3 else 0),
            gain=(config_b >> 5) & 0x7,
            mode=Mode(min(mode & 0x3, 2)),
        )


def decode_data(block: list[int]) -> np.ndarray:
    """Six data bytes (X, Z, Y big-endian) -> counts in x, y, z order, shape (3,), int."""
    counts = np.zeros(3, dtype=int)
    for slot, axis in enumerate(REGISTER_AXES):
        counts[axis] = to_signed((block[2 * slot] << 8) | block[2 * slot + 1], 16)
    return counts


class HMC5883L(Sensor):
    """Driver: checks the identity, applies ``settings``, and reads one six-byte block per sample.

    ``read()`` polls Status: no RDY -> ``Reading(ready=False)``; otherwise reads X, Z, Y in one block. In single
    mode it triggers the next measurement after each read. ``axis_scale`` (3,) multiplies each axis (self-test).
    """

    def __init__(
        self,
        bus: I2CBus,
        address: int = DEFAULT_ADDRESS,
        orientation: Any = None,
        *,
        settings: HMC5883LSettings | None = None,
        retry: RetryPolicy | None = None,
        sleep: Callable[[float], None] | None = None,
        axis_scale: Any = (1.0, 1.0, 1.0),
    ) -> None:
        self._attach(bus, address, orientation, retry, sleep)
        self.axis_scale = np.asarray(axis_scale, dtype=float)
        self.check_identity()
        self.configure(settings or HMC5883LSettings())

    def check_identity(self) -> None:
        found = bytes(self.device.read_block(REG_ID, 3))
        if found != IDENTITY:
            raise SensorError(
                f"no HMC5883L at {self.device.address:#04x}: identification registers read "
                f"{found!r}, expected {IDENTITY!r} (check the address with i2cdetect; QMC5883L "
                "modules sold as HMC5883L sit at 0x0D and need --sensor qmc5883l)"
            )

    def configure(self, settings: HMC5883LSettings) -> None:
        """Write Config A, Config B and Mode (Mode last: it starts the measurement)."""
        previous = getattr(self, "settings", None)
        old_gain = previous.gain if previous else self.device.read_byte(REG_CONFIG_B) >> 5
        self.settings = settings
        # the datasheet: the first measurement after a gain change is still at the old gain, so it is discarded
        self._discard = int(old_gain != settings.gain)
        self.device.write_byte(REG_CONFIG_A, settings.config_a)
        self.device.write_byte(REG_CONFIG_B, settings.config_b)
        self.device.write_byte(REG_MODE, int(settings.mode))

    @property
    def ut_per_count(self) -> float:
        return 100.0 / LSB_PER_GAUSS[self.settings.gain]

    def read_counts(self) -> tuple[np.ndarray | None, int]:
        """Poll Status, then read the six data bytes if RDY: (counts x, y, z or None, status byte). None also for
        the measurement discarded after a gain change."""
        status = self.device.read_byte(REG_STATUS)
        if not status & STATUS_RDY:
            return None, status
        counts = decode_data(self.device.read_block(REG_DATA, 6))
        if self.settings.mode == Mode.SINGLE:
            self.device.write_byte(REG_MODE, int(Mode.SINGLE))
        if self._discard:
            self._discard -= 1
            return None, status & ~STATUS_RDY
        return counts, status

    def _read(self) -> Reading:
        counts, _ = self.read_counts()
        if counts is None:
            return NOT_READY
        if np.any(counts == OVERFLOW):
            return Reading(overflow=True, raw=counts)
        return Reading(mag_ut=counts * self.ut_per_count * self.axis_scale, raw=counts)

    def self_test(
        self, gain: int = 5, *, discard: int = 0, average: int = 1, max_polls: int = 50, poll_s: float = 0.07
    ) -> SelfTestResult:
        """Datasheet self-test: positive then negative bias at ``gain``, each the mean of ``average`` readings
        after discarding ``discard`` more (the one after a gain change is always dropped); the configuration in force
        before the test is restored afterwards, whatever happens."""
        saved = self.settings
        try:
            readings = {}
            for bias in (Bias.POSITIVE, Bias.NEGATIVE):
                self.configure(HMC5883LSettings(averaging=8, rate_hz=15.0, bias=bias, gain=gain, mode=Mode.CONTINUOUS))
                readings[bias] = self._mean_counts(discard, average, max_polls, poll_s)
        finally:
            self.configure(saved)
        return evaluate(readings[Bias.POSITIVE], readings[Bias.NEGATIVE], gain)

    def _mean_counts(self, discard: int, average: int, max_polls: int, poll_s: float) -> np.ndarray:
        taken: list[np.ndarray] = []
        polls = 0
        while len(taken) < discard + average:
            counts, _ = self.read_counts()
            if counts is None:
                polls += 1
                if polls > max_polls:
                    raise SensorError(f"HMC5883L at {self.device.address:#04x}: no data ready during self-test")
                self.device.sleep(poll_s)
                continue
            taken.append(counts)
        kept = np.array(taken[discard:], dtype=float)
        mean = kept.mean(axis=0)
        mean[np.any(kept == OVERFLOW, axis=0)] = OVERFLOW  # one overflow spoils the axis: the test must fail
        return mean
