"""``magnet sample``: read a sensor (or its emulator fed by the simulator) and print CSV.

Columns: ``t_s,mx,my,mz`` (uT, body frame), then ``ax,ay,az`` (m/s^2) for sensors with an accelerometer and
``gx,gy,gz`` (rad/s, body frame) for sensors with a gyroscope; with
``--emulate`` also the truth ``true_heading_deg,pitch_deg,roll_deg``, and with ``--trajectory turntable`` the
``mounting,heading_deg`` (table angle) columns that ``magnet fit --method turntable`` reads. The sensor is read
through the bounded read loop (``magnet.edge.readloop``): overflowed readings and failed reads are left out, counted and
reported on stderr; after ``GIVE_UP_AFTER`` failed reads in a row the command stops with a one-line error (exit 2).
``--emulate`` never sleeps; real hardware is paced at ``--rate``.
"""

from __future__ import annotations

import argparse
import dataclasses
import logging
import sys
import time
from collections.abc import Callable, Iterator
from typing import Any

import smbus2

from magnet.drivers import I2CBus, Reading, Sensor, has_accelerometer, has_gyroscope, open_sensor
from magnet.edge.readloop import ReadLoop
from magnet.emulators import emulator_for
from magnet.frames import orientation_matrix
from magnet.retry import RetryPolicy
from magnet.simulator import SensorStream, Trajectory
from services.common import sim_options

log = logging.getLogger("magnet.sample")

SENSOR_NAMES = (
    "hmc5883l",
    "lsm303dlh",
    "ak09918c+bma456",
    "qmc5883l",
    "icm20948",
    "lsm9ds1",
    "mpu6050+hmc5883l",
    "mpu6050+qmc5883l",
)
MAX_NOT_READY_POLLS = 200
#: a one-shot command gives up after this many failed reads in a row (about 3 s of backoff)
GIVE_UP_AFTER = 10


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--sensor", required=True, choices=SENSOR_NAMES, help="which chip")
    parser.add_argument("--bus", type=int, help="I2C bus number of a real sensor (/dev/i2c-N; 1 on a Raspberry Pi)")
    parser.add_argument("--address", type=lambda s: int(s, 0), help="I2C address (default: the chip's, e.g. 0x1e)")
    parser.add_argument(
        "--orientation",
        default=None,
        help="mounting: none, yaw90, roll180, roll180_yaw90, ... or 9 numbers of a 3x3 matrix",
    )
    parser.add_argument("--emulate", action="store_true", help="read the chip's emulator fed by the simulator")
    parser.add_argument("--count", type=int, default=100, help="samples to print (default 100)")
    parser.add_argument("--rate", type=float, default=50.0, help="samples per second (default 50)")
    sim_options.add_simulator_arguments(parser)


@dataclasses.dataclass(frozen=True)
class SampleSettings:
    """What ``magnet sample`` reads, checked in one place. count <= 0: until stopped; rate_hz paces hardware."""

    sensor: str
    bus: int | None = None
    address: int | None = None
    orientation: str | None = None
    emulate: bool = False
    count: int = 100
    rate_hz: float = 50.0
    simulator: sim_options.SimulatorSettings = dataclasses.field(default_factory=sim_options.SimulatorSettings)

    def __post_init__(self) -> None:
        if self.sensor not in SENSOR_NAMES:
            raise ValueError(f"unknown --sensor {self.sensor!r}: use one of {', '.join(SENSOR_NAMES)}")
        if not self.rate_hz > 0:
            raise ValueError(f"--rate must be > 0, got {self.rate_hz}")
        if not self.emulate and self.bus is None:
            raise ValueError("a real sensor needs --bus N (1 on a Raspberry Pi), or use --emulate")
        orientation_matrix(self.orientation)  # ValueError naming the accepted forms

    @classmethod
    def from_args(cls, args: argparse.Namespace) -> SampleSettings:
        return cls(
            sensor=args.sensor,
            bus=args.bus,
            address=args.address,
            orientation=args.orientation,
            emulate=bool(args.emulate),
            count=int(args.count),
            rate_hz=float(args.rate),
            simulator=sim_options.SimulatorSettings.from_args(args),
        )

    @property
    def turntable(self) -> bool:
        return self.emulate and self.simulator.trajectory is Trajectory.TURNTABLE


def open_bus(settings: SampleSettings, source: Any = None, **emulator_options: Any) -> I2CBus:
    """The emulated bus (``--emulate``) or ``smbus2.SMBus(--bus)``."""
    if settings.emulate:
        return emulator_for(settings.sensor, source, **emulator_options)
    return smbus2.SMBus(settings.bus)


def _header(has_acc: bool, emulate: bool, turntable: bool, has_gyr: bool = False) -> list[str]:
    columns = ["t_s", "mx", "my", "mz"] + (["ax", "ay", "az"] if has_acc else [])
    columns += ["gx", "gy", "gz"] if has_gyr else []
    if emulate:
        columns += ["true_heading_deg", "pitch_deg", "roll_deg"]
    if turntable:
        columns += ["mounting", "heading_deg"]
    return columns


def read_loop(sensor: Sensor, settings: SampleSettings, sleep: Callable[[float], None] = time.sleep) -> ReadLoop:
    """The bounded read loop (``magnet.edge.readloop``) for the command: never sleeps when emulated; gives up after
    ``GIVE_UP_AFTER`` failed reads in a row with a clear error."""
    poll_s = 0.0 if settings.emulate else min(0.1 / settings.rate_hz, 0.005)
    policy = RetryPolicy(
        initial_s=0.01, max_s=1.0, poll_s=poll_s, max_polls=MAX_NOT_READY_POLLS, give_up_after=GIVE_UP_AFTER
    )
    return ReadLoop(sensor.read, clock=time.monotonic, sleep=sleep, policy=policy)


def _readings(loop: ReadLoop, settings: SampleSettings) -> Iterator[tuple[float, Reading]]:
    """(t_s, reading) for each good sample; paced at --rate on hardware, unpaced when emulated."""
    period = 1.0 / settings.rate_hz
    start = time.monotonic()
    taken = 0
    while settings.count <= 0 or taken < settings.count:
        if not settings.emulate:
            delay = start + taken * period - time.monotonic()
            if delay > 0:
                time.sleep(delay)
        reading = loop.next()
        if reading is None:  # pragma: no cover - next() without stop returns a reading or raises
            return
        taken += 1
        yield time.monotonic() - start, reading


def _fmt(values: Any) -> list[str]:
    return [f"{v:.4f}" for v in values]


def _announce_turntable(stream: SensorStream) -> None:
    earth = stream.earth
    print(
        f"magnet sample: turntable field: horizontal {earth.horizontal_ut:.3f} uT, vertical (up) "
        f"{-earth.down_ut:.3f} uT: use magnet fit --method turntable --horizontal {earth.horizontal_ut:.3f} "
        f"--vertical {-earth.down_ut:.3f}",
        file=sys.stderr,
    )


def sample(settings: SampleSettings) -> int:
    """Print the CSV for the settings on stdout; returns the exit status."""
    stream = settings.simulator.sensor_stream(settings.count, settings.rate_hz) if settings.emulate else None
    bus = open_bus(settings, stream)
    sensor = open_sensor(settings.sensor, bus, settings.address, settings.orientation)
    has_acc = has_accelerometer(settings.sensor)
    has_gyr = has_gyroscope(settings.sensor)
    if settings.turntable and stream is not None:
        _announce_turntable(stream)
    out = sys.stdout
    out.write(",".join(_header(has_acc, settings.emulate, settings.turntable, has_gyr)) + "\n")
    loop = read_loop(sensor, settings)
    try:
        for t_s, reading in _readings(loop, settings):
            truth = stream.last_truth if stream is not None else {}
            row = [f"{truth.get('t_s', t_s):.4f}", *_fmt(reading.mag_ut)]
            if has_acc:
                row += _fmt(reading.acc_ms2) if reading.acc_ms2 is not None else ["", "", ""]
            if has_gyr:
                row += [f"{v:.6f}" for v in reading.gyr_rads] if reading.gyr_rads is not None else ["", "", ""]
            if settings.emulate:
                row += _fmt([truth["heading_deg"], truth["pitch_deg"], truth["roll_deg"]])
            if settings.turntable:
                row += [str(truth["mounting"]), f"{truth['table_deg']:.4f}"]
            out.write(",".join(row) + "\n")
    finally:
        out.flush()
        stats = loop.health
        if stats.errors or stats.overflows:
            log.warning(
                "left out %d failed reads (%s) and %d overflows; sensor health: %s",
                stats.errors,
                stats.errors_by_cause,
                stats.overflows,
                sensor.health.as_dict(),
            )
    return 0


def run(args: argparse.Namespace) -> int:
    return sample(SampleSettings.from_args(args))
