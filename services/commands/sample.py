"""``magnet sample``: read a sensor (or its emulator fed by the simulator) and print CSV.

Columns: ``t_s,mx,my,mz`` (uT, body frame), then ``ax,ay,az`` (m/s^2) for sensors with an accelerometer; with
``--emulate`` also the truth ``true_heading_deg,pitch_deg,roll_deg``, and with ``--trajectory turntable`` the
``mounting,heading_deg`` (table angle) columns that ``magnet fit --method turntable`` reads. Samples whose reading
overflowed or failed are left out and counted on stderr. ``--emulate`` never sleeps; real hardware is paced at
``--rate``.
"""

from __future__ import annotations

import argparse
import logging
import sys
import time
from typing import Any, Iterator

from services.common import sim_options

log = logging.getLogger("magnet.sample")

SENSOR_NAMES = ("hmc5883l", "lsm303dlh", "ak09918c+bma456", "qmc5883l")
MAX_NOT_READY_POLLS = 200


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--sensor", required=True, choices=SENSOR_NAMES, help="which chip")
    parser.add_argument("--bus", type=int, help="I2C bus number of a real sensor (/dev/i2c-N; 1 on a Raspberry Pi)")
    parser.add_argument("--address", type=lambda s: int(s, 0), help="I2C address (default: the chip's, e.g. 0x1e)")
    parser.add_argument("--orientation", default=None,
                        help="mounting: none, yaw90, roll180, roll180_yaw90, ... or 9 numbers of a 3x3 matrix")
    parser.add_argument("--emulate", action="store_true", help="read the chip's emulator fed by the simulator")
    parser.add_argument("--count", type=int, default=100, help="samples to print (default 100)")
    parser.add_argument("--rate", type=float, default=50.0, help="samples per second (default 50)")
    sim_options.add_simulator_arguments(parser)


def sensor_stream(args: argparse.Namespace, count: int):
    """The simulator's ``SensorStream`` for the options (``count`` samples of trajectory at --rate)."""
    return sim_options.sensor_stream(args, count, args.rate)


def open_bus(args: argparse.Namespace, source: Any = None, **emulator_options: Any) -> Any:
    """The emulated bus (``--emulate``) or ``smbus2.SMBus(--bus)``."""
    if args.emulate:
        from magnet.emulators import emulator_for
        return emulator_for(args.sensor, source, **emulator_options)
    if args.bus is None:
        raise ValueError("a real sensor needs --bus N (1 on a Raspberry Pi), or use --emulate")
    import smbus2
    return smbus2.SMBus(args.bus)


def _header(has_acc: bool, emulate: bool, turntable: bool) -> list[str]:
    columns = ["t_s", "mx", "my", "mz"] + (["ax", "ay", "az"] if has_acc else [])
    if emulate:
        columns += ["true_heading_deg", "pitch_deg", "roll_deg"]
    if turntable:
        columns += ["mounting", "heading_deg"]
    return columns


def _readings(sensor: Any, args: argparse.Namespace, skipped: dict[str, int]) -> Iterator[tuple[float, Any]]:
    """(t_s, reading) for each good sample; paced at --rate on hardware, unpaced when emulated."""
    period = 1.0 / args.rate
    start = time.monotonic()
    taken = 0
    while args.count <= 0 or taken < args.count:
        if not args.emulate:
            delay = start + taken * period - time.monotonic()
            if delay > 0:
                time.sleep(delay)
        reading = sensor.read()
        polls = 0
        while not reading.ready and not reading.failed and polls < MAX_NOT_READY_POLLS:
            polls += 1
            if not args.emulate:
                time.sleep(min(period / 10, 0.005))
            reading = sensor.read()
        taken += 1
        cause = "failed" if reading.failed else "overflow" if reading.overflow else \
            "not ready" if reading.mag_ut is None else ""
        if cause:
            skipped[cause] = skipped.get(cause, 0) + 1
            continue
        yield time.monotonic() - start, reading


def _fmt(values: Any) -> list[str]:
    return [f"{v:.4f}" for v in values]


def run(args: argparse.Namespace) -> int:
    from magnet.drivers import has_accelerometer, open_sensor

    if args.rate <= 0:
        raise ValueError(f"--rate must be > 0, got {args.rate}")
    stream = sensor_stream(args, args.count) if args.emulate else None
    turntable = bool(args.emulate and args.trajectory.strip().lower() == "turntable")
    bus = open_bus(args, stream)
    sensor = open_sensor(args.sensor, bus, args.address, args.orientation)
    has_acc = has_accelerometer(args.sensor)
    if turntable:
        earth = stream.earth
        print(f"magnet sample: turntable field: horizontal {earth.horizontal_ut:.3f} uT, vertical (up) "
              f"{-earth.down_ut:.3f} uT: use magnet fit --method turntable --horizontal {earth.horizontal_ut:.3f} "
              f"--vertical {-earth.down_ut:.3f}", file=sys.stderr)
    out = sys.stdout
    out.write(",".join(_header(has_acc, args.emulate, turntable)) + "\n")
    skipped: dict[str, int] = {}
    for t_s, reading in _readings(sensor, args, skipped):
        truth = stream.last_truth if stream is not None else {}
        row = [f"{truth.get('t_s', t_s):.4f}"] + _fmt(reading.mag_ut)
        if has_acc:
            row += _fmt(reading.acc_ms2) if reading.acc_ms2 is not None else ["", "", ""]
        if args.emulate:
            row += _fmt([truth["heading_deg"], truth["pitch_deg"], truth["roll_deg"]])
        if turntable:
            row += [str(truth["mounting"]), f"{truth['table_deg']:.4f}"]
        out.write(",".join(row) + "\n")
    out.flush()
    if skipped:
        log.warning("left out %s; sensor health: %s", ", ".join(f"{n} {k}" for k, n in skipped.items()),
                    sensor.health.as_dict())
    return 0
