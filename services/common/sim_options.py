"""The simulator's command-line options, shared by ``magnet sample`` and ``magnet edge``, and what they build.

``--seed``, ``--trajectory`` (still: spin, turntable, tumble, tenface; moving, with linear acceleration and a gyroscope:
multirotor, car, figure8, fast-tumble, the walks and the planar boat and robot), ``--hard-iron X,Y,Z`` (uT),
``--soft-iron`` (3 diagonal or 9 row-major numbers), ``--noise-ut``, ``--gyro-bias X,Y,Z`` (rad/s), ``--gyro-noise``
(rad/s RMS per sample), ``--location LAT,LON[,ALT_M]``, ``--date`` (default: the simulator's fixed date, so that the
same seed gives the same data on any day). Declared once as the fields of ``SimulatorSettings``
(``services.common.options``); a command with other defaults subclasses it and redeclares ``seed_option(N)`` /
``noise_option(X)`` (``magnet edge``).
"""

from __future__ import annotations

import argparse
import dataclasses
from typing import Any

import numpy as np

from magnet.earth.location import Location
from magnet.simulator import (
    DEFAULT_LOCATION,
    PATH_TRAJECTORIES,
    Disturbances,
    HardIronChange,
    SensorErrors,
    SensorStream,
    SimulatorConfig,
    Trajectory,
)
from services.common.options import Check, add_options, check_options, from_args, option


def parse_floats(text: str, counts: tuple[int, ...], name: str) -> np.ndarray:
    """Comma-separated numbers, as many as one of ``counts``; ValueError naming the option (``name``, "" for an
    option declared with ``services.common.options``, which names it) otherwise."""
    try:
        values = [float(v) for v in text.replace(" ", "").split(",") if v]
    except ValueError:
        raise ValueError(f"{name} must be comma-separated numbers, got {text!r}".lstrip()) from None
    if len(values) not in counts:
        raise ValueError(f"{name} needs {' or '.join(map(str, counts))} numbers, got {len(values)}".lstrip())
    return np.asarray(values)


def parse_soft_iron(text: str) -> np.ndarray:
    """3 numbers (diagonal) or 9 (row-major 3x3) -> (3, 3)."""
    values = parse_floats(text, (3, 9), "")
    return np.diag(values) if values.size == 3 else values.reshape(3, 3)


def parse_trajectory(text: str) -> Trajectory:
    try:
        return Trajectory(text.strip().lower())
    except ValueError:
        raise ValueError(
            f"unknown --trajectory {text!r}: use one of {', '.join(t.value for t in Trajectory)}"
        ) from None


#: the simulator's place when no --location is given (Kyiv)
DEFAULT_PLACE = Location.parse(DEFAULT_LOCATION)
GROUP = "simulator (with --emulate)"


def _hard_iron(text: str) -> tuple[float, ...]:
    return tuple(parse_floats(text, (3,), "").tolist())


def _soft_iron(text: str) -> tuple[float, ...]:
    return tuple(parse_soft_iron(text).ravel().tolist())


def _iron_change(text: str) -> tuple[float, ...]:
    values = parse_floats(text, (4,), "")
    if values[0] < 0:
        raise ValueError(f"T_S must be >= 0 seconds, got {values[0]:g}")
    return tuple(values.tolist())


def _gyro_bias(text: str) -> tuple[float, ...]:
    return tuple(parse_floats(text, (3,), "").tolist())


def _not_negative(value: Any) -> str | None:
    ok = isinstance(value, (int, float)) and not isinstance(value, bool) and value >= 0
    return None if ok else "must be >= 0"


def _count(n: int) -> Check:
    def check(value: Any) -> str | None:
        return None if len(value) == n else f"needs {n} numbers"

    return check


def seed_option(default: int) -> Any:
    """``--seed``, with the command's own default (``magnet sample`` 0, ``magnet edge`` 1)."""
    return option(default, "--seed", help="simulator seed: same seed, same data", group=GROUP)


def noise_option(default: float) -> Any:
    """``--noise-ut``, with the command's own default (``magnet sample`` 0, ``magnet edge`` 0.3)."""
    return option(default, "--noise-ut", metavar="UT", help="noise, uT RMS", check=_not_negative, group=GROUP)


@dataclasses.dataclass(frozen=True)
class SimulatorSettings:
    """The simulator options, declared once (``services.common.options``). hard_iron_ut (3,) uT; soft_iron 9 numbers
    row-major (3x3); noise_ut uT RMS; gyro_bias_rads (3,) rad/s; gyro_noise_rads rad/s RMS; location None: Kyiv
    (``DEFAULT_PLACE``, see ``place_location``); date as given (None: the simulator's)."""

    seed: int = seed_option(0)
    trajectory: Trajectory = option(
        Trajectory.TUMBLE,
        "--trajectory",
        parse=parse_trajectory,
        show_default=False,
        help="still: spin, turntable, tumble, tenface; moving: multirotor, car, figure8, fast-tumble, walk-pocket, "
        "walk-hand, walk-texting, walk-phoning, running, boat, robot (default tumble)",
        group=GROUP,
    )
    hard_iron_ut: tuple[float, ...] = option(
        (0.0, 0.0, 0.0),
        "--hard-iron",
        metavar="X,Y,Z",
        parse=_hard_iron,
        show_default=False,
        check=_count(3),
        help="hard iron X,Y,Z in uT",
        group=GROUP,
    )
    soft_iron: tuple[float, ...] = option(
        (1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0),
        "--soft-iron",
        metavar="NUMBERS",
        parse=_soft_iron,
        show_default=False,
        check=_count(9),
        help="soft iron: 3 diagonal or 9 row-major numbers",
        group=GROUP,
    )
    noise_ut: float = noise_option(0.0)
    gyro_bias_rads: tuple[float, ...] = option(
        (0.0, 0.0, 0.0),
        "--gyro-bias",
        metavar="X,Y,Z",
        parse=_gyro_bias,
        show_default=False,
        check=_count(3),
        help="gyroscope bias X,Y,Z in rad/s (default none)",
        group=GROUP,
    )
    gyro_noise_rads: float = option(
        0.0, "--gyro-noise", metavar="RADS", check=_not_negative, help="gyroscope noise, rad/s RMS", group=GROUP
    )
    location: Location | None = option(
        None,
        "--location",
        parse=Location.parse,
        metavar="LAT,LON[,ALT_M]",
        help=f"the simulated device's place (default Kyiv, {DEFAULT_LOCATION}); magnet edge also sends it in its "
        "raw messages",
        group=GROUP,
    )
    date: str | None = option(None, "--date", help="YYYY-MM-DD or decimal year (default: the simulator's)", group=GROUP)
    disturbances: bool = option(
        False,
        "--disturbances",
        help="steel doors and parked cars passed on the way (walks, car, boat, robot; docs/field-motions.md)",
        group=GROUP,
    )
    iron_change: tuple[float, ...] | None = option(
        None,
        "--iron-change",
        metavar="T_S,X,Y,Z",
        parse=_iron_change,
        show_default=False,
        help="from T_S seconds on the hard iron is X,Y,Z uT (an in-service recalibration to make)",
        group=GROUP,
    )

    def __post_init__(self) -> None:
        check_options(self)
        self.config_extras()  # a trajectory without a path refuses --disturbances now, not when it first samples

    @classmethod
    def from_args(cls, args: argparse.Namespace) -> SimulatorSettings:
        """The settings of the options ``add_simulator_arguments`` added, checked."""
        return from_args(cls, args)

    @property
    def place_location(self) -> Location:
        """Where the simulated device is: --location, else ``DEFAULT_PLACE``."""
        return DEFAULT_PLACE if self.location is None else self.location

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
        where = self.place_location
        return {
            "lat_deg": where.lat_deg,
            "lon_deg": where.lon_deg,
            "alt_m": where.alt_m,
            **({"date": self.date} if self.date else {}),
        }

    def config_extras(self) -> dict[str, Any]:
        """``disturbances`` and ``hard_iron_change`` of the simulator's config (ValueError: --disturbances with a
        trajectory that does not follow a path)."""
        if self.disturbances and self.trajectory not in PATH_TRAJECTORIES:
            names = ", ".join(sorted(t.value for t in PATH_TRAJECTORIES))
            raise ValueError(f"--disturbances needs a --trajectory along a path ({names})")
        change = None
        if self.iron_change is not None:
            change = HardIronChange(self.iron_change[0], np.array(self.iron_change[1:]))
        return {"disturbances": Disturbances() if self.disturbances else None, "hard_iron_change": change}

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
                **self.config_extras(),
            )
        )


def add_simulator_arguments(
    parser: argparse.ArgumentParser, settings: type[SimulatorSettings] = SimulatorSettings
) -> None:
    """The simulator options of ``settings`` (``SimulatorSettings`` or a subclass with other defaults), in their
    own group of the help."""
    add_options(parser, settings)
