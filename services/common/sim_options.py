"""The simulator's command-line options, shared by ``magnet sample`` and ``magnet edge``, and what they build.

``--seed``, ``--trajectory`` (still: spin, turntable, tumble, tenface; moving, with linear acceleration and a gyroscope:
multirotor, car, figure8, fast-tumble), ``--hard-iron X,Y,Z`` (uT), ``--soft-iron`` (3 diagonal or 9 row-major
numbers), ``--noise-ut``, ``--gyro-bias X,Y,Z`` (rad/s), ``--gyro-noise`` (rad/s RMS per sample), ``--location
LAT,LON[,ALT_M]``, ``--date`` (default: the simulator's fixed date, so that the same seed gives the same data on any
day). ``SimulatorSettings.from_args`` checks them all at once.
"""

from __future__ import annotations

import argparse
import dataclasses
from typing import Any

import numpy as np

from magnet.place import Location
from magnet.simulator import SensorErrors, SensorStream, SimulatorConfig, Trajectory


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


def parse_trajectory(text: str) -> Trajectory:
    try:
        return Trajectory(text.strip().lower())
    except ValueError:
        raise ValueError(
            f"unknown --trajectory {text!r}: use one of {', '.join(t.value for t in Trajectory)}"
        ) from None


#: the simulator's place when no --location is given (Kyiv)
DEFAULT_LOCATION = "50.45,30.52"


def add_simulator_arguments(parser: argparse.ArgumentParser, *, seed: int = 0, noise_ut: float = 0.0) -> None:
    group = parser.add_argument_group("simulator (with --emulate)")
    group.add_argument("--seed", type=int, default=seed, help=f"simulator seed: same seed, same data (default {seed})")
    group.add_argument(
        "--trajectory",
        default="tumble",
        help="still: spin, turntable, tumble, tenface; moving: multirotor, car, figure8, fast-tumble (default tumble)",
    )
    group.add_argument("--hard-iron", default="0,0,0", help="hard iron X,Y,Z in uT")
    group.add_argument("--soft-iron", default="1,1,1", help="soft iron: 3 diagonal or 9 row-major numbers")
    group.add_argument("--noise-ut", type=float, default=noise_ut, help=f"noise, uT RMS (default {noise_ut:g})")
    group.add_argument("--gyro-bias", default="0,0,0", help="gyroscope bias X,Y,Z in rad/s (default none)")
    group.add_argument("--gyro-noise", type=float, default=0.0, help="gyroscope noise, rad/s RMS (default 0)")
    group.add_argument(
        "--location",
        default=None,
        help=f"LAT,LON[,ALT_M] (default Kyiv, {DEFAULT_LOCATION}); magnet edge also sends it in its raw messages",
    )
    group.add_argument("--date", default=None, help="YYYY-MM-DD or decimal year (default: the simulator's)")


@dataclasses.dataclass(frozen=True)
class SimulatorSettings:
    """The simulator options, checked. hard_iron_ut (3,) uT; soft_iron 9 numbers row-major (3x3); noise_ut uT RMS;
    gyro_bias_rads (3,) rad/s; gyro_noise_rads rad/s RMS; location (lat_deg, lon_deg, alt_m); date as given (None:
    the simulator's)."""

    seed: int = 0
    trajectory: Trajectory = Trajectory.TUMBLE
    hard_iron_ut: tuple[float, ...] = (0.0, 0.0, 0.0)
    soft_iron: tuple[float, ...] = (1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0)
    noise_ut: float = 0.0
    location: tuple[float, float, float] = (50.45, 30.52, 0.0)
    date: str | None = None
    gyro_bias_rads: tuple[float, ...] = (0.0, 0.0, 0.0)
    gyro_noise_rads: float = 0.0

    def __post_init__(self) -> None:
        if not self.noise_ut >= 0:
            raise ValueError(f"--noise-ut must be >= 0, got {self.noise_ut}")
        if not self.gyro_noise_rads >= 0:
            raise ValueError(f"--gyro-noise must be >= 0, got {self.gyro_noise_rads}")
        if len(self.hard_iron_ut) != 3 or len(self.soft_iron) != 9:
            raise ValueError("hard iron needs 3 numbers and soft iron 9")

    @classmethod
    def from_args(cls, args: argparse.Namespace) -> SimulatorSettings:
        return cls(
            seed=int(args.seed),
            trajectory=parse_trajectory(args.trajectory),
            hard_iron_ut=tuple(parse_floats(args.hard_iron, (3,), "--hard-iron").tolist()),
            soft_iron=tuple(parse_soft_iron(args.soft_iron).ravel().tolist()),
            noise_ut=float(args.noise_ut),
            location=Location.parse(args.location or DEFAULT_LOCATION).as_tuple(),
            date=args.date,
            gyro_bias_rads=tuple(parse_floats(args.gyro_bias, (3,), "--gyro-bias").tolist()),
            gyro_noise_rads=float(args.gyro_noise),
        )

    def errors(self) -> SensorErrors:
        """The simulator's ``SensorErrors``."""
        return SensorErrors(
            hard_iron_ut=np.array(self.hard_iron_ut),
            soft_iron=np.array(self.soft_iron).reshape(3, 3),
            noise_ut=self.noise_ut,
            gyro_bias_rads=np.array(self.gyro_bias_rads),
            gyro_noise_rads=self.gyro_noise_rads,
        )

    def place(self) -> dict[str, Any]:
        """lat_deg, lon_deg, alt_m and (when given) date, as the simulator's keyword arguments."""
        lat, lon, alt = self.location
        return {"lat_deg": lat, "lon_deg": lon, "alt_m": alt, **({"date": self.date} if self.date else {})}

    def sensor_stream(self, count: int, rate_hz: float) -> SensorStream:
        """The simulator's ``SensorStream``: ``count`` samples of trajectory at ``rate_hz``."""
        return SensorStream(
            SimulatorConfig(
                trajectory=self.trajectory,
                rate_hz=rate_hz,
                count=max(count, 1),
                errors=self.errors(),
                seed=self.seed,
                **self.place(),
            )
        )
