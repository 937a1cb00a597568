"""The simulator's command-line options, shared by ``magnet sample`` and ``magnet edge``, and what they build.

``--seed``, ``--trajectory`` (still: spin, turntable, tumble, tenface; moving, with linear acceleration and a gyroscope:
multirotor, car, figure8, fast-tumble), ``--hard-iron X,Y,Z`` (uT), ``--soft-iron`` (3 diagonal or 9 row-major
numbers), ``--noise-ut``, ``--gyro-bias X,Y,Z`` (rad/s), ``--gyro-noise`` (rad/s per sample), ``--location LAT,LON[,ALT_M]``, ``--date`` (default: the simulator's fixed
date, so that the same seed gives the same data on any day).
"""

from __future__ import annotations

import argparse

import numpy as np


def parse_floats(text: str, counts: tuple[int, ...], name: str) -> np.ndarray:
    """Comma-separated numbers, as many as one of ``counts``; ValueError naming the option otherwise."""
    try:
        values = [float(v) for v in text.replace(" ", "").split(",") if v]
    except ValueError:
        raise ValueError(f"{name} must be comma-separated numbers, got {text!r}") from None
    if len(values) not in counts:
        raise ValueError(f"{name} needs {' or '.join(map(str, counts))} numbers, got {len(values)}")
    return np.asarray(values)


def parse_soft_iron(text: str) -> np.ndarray:
    """3 numbers (diagonal) or 9 (row-major 3x3) -> (3, 3)."""
    values = parse_floats(text, (3, 9), "--soft-iron")
    return np.diag(values) if values.size == 3 else values.reshape(3, 3)


def add_simulator_arguments(parser: argparse.ArgumentParser, *, seed: int = 0, noise_ut: float = 0.0) -> None:
    group = parser.add_argument_group("simulator (with --emulate)")
    group.add_argument("--seed", type=int, default=seed, help=f"simulator seed: same seed, same data (default {seed})")
    group.add_argument("--trajectory", default="tumble",
                       help="still: spin, turntable, tumble, tenface; moving: multirotor, car, figure8, fast-tumble "
                            "(default tumble)")
    group.add_argument("--hard-iron", default="0,0,0", help="hard iron X,Y,Z in uT")
    group.add_argument("--soft-iron", default="1,1,1", help="soft iron: 3 diagonal or 9 row-major numbers")
    group.add_argument("--noise-ut", type=float, default=noise_ut, help=f"noise, uT RMS (default {noise_ut:g})")
    group.add_argument("--gyro-bias", default="0,0,0", help="gyroscope bias X,Y,Z in rad/s (default none)")
    group.add_argument("--gyro-noise", type=float, default=0.0, help="gyroscope noise, rad/s RMS (default 0)")
    group.add_argument("--location", default="50.45,30.52", help="LAT,LON[,ALT_M] (default Kyiv)")
    group.add_argument("--date", default=None, help="YYYY-MM-DD or decimal year (default: the simulator's)")


def sensor_errors(args: argparse.Namespace):
    """The simulator's ``SensorErrors`` from the options."""
    from magnet.simulator import SensorErrors

    if args.noise_ut < 0:
        raise ValueError(f"--noise-ut must be >= 0, got {args.noise_ut}")
    if args.gyro_noise < 0:
        raise ValueError(f"--gyro-noise must be >= 0, got {args.gyro_noise}")
    return SensorErrors(hard_iron_ut=parse_floats(args.hard_iron, (3,), "--hard-iron"),
                        soft_iron=parse_soft_iron(args.soft_iron), noise_ut=float(args.noise_ut),
                        gyro_bias_rads=parse_floats(args.gyro_bias, (3,), "--gyro-bias"),
                        gyro_noise_rads=float(args.gyro_noise))


def simulator_place(args: argparse.Namespace) -> dict:
    """lat_deg, lon_deg, alt_m and (when given) date, as the simulator's keyword arguments."""
    from magnet.geomag import parse_location

    lat, lon, alt = parse_location(args.location)
    return {"lat_deg": lat, "lon_deg": lon, "alt_m": alt, **({"date": args.date} if args.date else {})}


def sensor_stream(args: argparse.Namespace, count: int, rate_hz: float):
    """The simulator's ``SensorStream`` for the options: ``count`` samples of trajectory at ``rate_hz``."""
    from magnet.simulator import SensorStream, SimulatorConfig, Trajectory

    try:
        trajectory = Trajectory(args.trajectory.strip().lower())
    except ValueError:
        raise ValueError(f"unknown --trajectory {args.trajectory!r}: use one of "
                         f"{', '.join(t.value for t in Trajectory)}") from None
    return SensorStream(SimulatorConfig(trajectory=trajectory, rate_hz=rate_hz, count=max(count, 1),
                                        errors=sensor_errors(args), seed=args.seed, **simulator_place(args)))
