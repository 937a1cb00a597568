"""``magnet edge``'s settings, declared once (``services.common.options``): each field of ``EdgeSettings`` is its
option (flag, default, help, check); ``add_arguments`` builds the argparse options from them and
``EdgeSettings.from_args`` reads them back, checked. Each source declares its own options (``MavlinkOptions``,
``Ros2SourceOptions``, ``ReplayOptions``, ``FleetOptions``, ``SimulatorOptions``, ``ChipOptions``: its flags, whether
they name it, what it refuses of the others) and ``EdgeSettings`` is all of them beside ``CommonOptions``; which
source the options name is ``EdgeSettings.source_kind`` (``SourceKind``), through one table, ``SOURCE_OPTIONS``."""

from __future__ import annotations

import argparse
import dataclasses
import enum
from collections.abc import Callable
from pathlib import Path
from typing import Any

from magnet import wire
from magnet.autopilot.mavlink_stream import MAX_PORT_DEVICES
from magnet.drivers import SENSORS, has_gyroscope
from magnet.earth.location import Location
from magnet.edge.replay import MAX_SPEED
from services.common.mavlink_options import baud_option, url_option
from services.common.options import Check, add_options, at_least, check_options, from_args, one_of, option, within
from services.common.ros2_options import Ros2Settings, add_ros2_arguments
from services.common.sim_options import (
    DEFAULT_PLACE,
    SimulatorSettings,
    add_simulator_arguments,
    noise_option,
    seed_option,
)
from services.common.zenoh_session import ZenohSettings, add_zenoh_arguments

SIMULATOR_SENSOR = "sim"
MAX_RATE_HZ = 100_000.0
MAX_DEVICES = 100_000
EDGE_DEVICES = 256  # devices that may appear while an edge runs, by default (docs/front-door.md)
ROS2_WHAT = "read a ROS 2 robot's MagneticField (and Imu) topics over rmw_zenoh (--mag-topic)"


class SourceKind(enum.StrEnum):
    """Where the edge's samples come from (``services.edge.sources.SOURCES`` opens each)."""

    MAVLINK = "mavlink"  # --mavlink URL: MAVLink vehicles
    ROS2 = "ros2"  # --ros2 --mag-topic T: a ROS 2 robot's topics
    REPLAY = "replay"  # --replay FILE: a recording at its own pace
    FLEET = "fleet"  # --emulate --devices N: N simulated devices
    SIMULATOR = "simulator"  # --emulate (--sensor sim): one simulated device, no register emulation
    CHIP = "chip"  # --sensor NAME (--bus N or --emulate): one chip through its driver


def _in_range(low: float, high: float, unit: str = "") -> Check:
    """A number in (low, high]."""

    def check(value: Any) -> str | None:
        good = isinstance(value, (int, float)) and not isinstance(value, bool) and low < value <= high
        return None if good else f"must be in ({low:g}, {high:g}]{unit}"

    return check


def _whole(low: int, high: int) -> Check:
    def check(value: Any) -> str | None:
        good = isinstance(value, int) and not isinstance(value, bool) and low <= value <= high
        return None if good else f"must be {low}..{high}"

    return check


def _seconds(value: Any) -> str | None:
    return None if value is None or value >= 0 else "must be >= 0 seconds"


def _device_id(value: Any) -> str | None:
    try:
        wire.validate_device_id(value)
    except ValueError as exc:
        return f"is not a device id ({exc})"
    return None


def _device_prefix(value: Any) -> str | None:
    return _device_id(f"{value}1-mag0")


@dataclasses.dataclass(frozen=True)
class EdgeSimulatorSettings(SimulatorSettings):
    """The simulator as ``magnet edge`` runs it: other defaults than ``magnet sample``'s (seed 1, 0.3 uT noise)."""

    seed: int = seed_option(1)
    noise_ut: float = noise_option(0.3)


@dataclasses.dataclass(frozen=True)
class CommonOptions:
    """What every source takes: the device id, the pace and the messages."""

    device: str = option(
        "dev", "--device", help="device id (one key chunk); a fleet uses <ID>-000, ...", check=_device_id
    )
    rate_hz: float = option(
        50.0, "--rate", metavar="RATE", help="samples per second per device", check=_in_range(0, MAX_RATE_HZ, " Hz")
    )
    batch: int = option(10, "--batch", help="samples per message", check=_whole(1, wire.MAX_BATCH_SAMPLES))
    duration_s: float | None = option(
        None, "--duration", parse=float, metavar="SECONDS", help="stop after this many seconds", check=_seconds
    )
    wire_version: int = option(
        wire.BINARY_ARRAYS_VERSION,
        "--wire",
        metavar="VERSION",
        help="message version: 2 binary arrays, 1 lists of numbers for old subscribers",
        check=lambda v: None if v in wire.VERSIONS else f"must be one of {', '.join(map(str, wire.VERSIONS))}",
    )
    max_devices: int = option(
        EDGE_DEVICES, "--max-devices", help="devices that may appear while running (MAVLink): a new one beyond "
        "them is dropped and counted (dropped[devices:limit])", check=_whole(1, MAX_DEVICES)
    )  # fmt: skip


@dataclasses.dataclass(frozen=True)
class ChipOptions:
    """A chip through its driver (``ChipSource``): on a bus, or emulated (and the simulator alone, ``--sensor sim``)."""

    sensor: str = option(
        SIMULATOR_SENSOR,
        "--sensor",
        help=f"chip name ({', '.join(SENSORS)}) or 'sim' for the simulator alone",
        check=one_of((*SENSORS, SIMULATOR_SENSOR)),
    )
    bus: int | None = option(None, "--bus", parse=int, help="I2C bus number of a real chip (/dev/i2c-N)")
    address: int | None = option(
        None, "--address", parse=lambda text: int(text, 0), help="I2C address of a real chip (e.g. 0x1e)"
    )
    emulate: bool = option(False, "--emulate", help="emulate the chip (or the fleet) instead of a bus")
    emulate_faults: float = option(
        0.0,
        "--emulate-faults",
        metavar="P",
        help="with --emulate and a chip, for tests: each I2C transfer after set-up fails with EIO "
        "with probability P (1: a dead bus)",
        check=within(0, 1, "a probability"),
    )

    @staticmethod
    def names_chip(s: EdgeSettings) -> bool:
        return True  # the last kind: what the options name when no other source is named

    @staticmethod
    def names_simulator(s: EdgeSettings) -> bool:
        return s.emulate and s.sensor == SIMULATOR_SENSOR

    @staticmethod
    def check_chip(s: EdgeSettings) -> None:
        _check_topics(s)
        if not s.emulate and s.bus is None:
            raise ValueError("a real sensor needs --bus N (or --emulate)")
        ChipOptions.check_simulated(s)

    @staticmethod
    def check_simulated(s: EdgeSettings) -> None:
        """What a fleet, the simulator and a chip share: fault injection only on an emulated chip, no speed-up where
        a gyroscope is simulated."""
        _check_topics(s)
        if s.emulate_faults and not s.emulated_chip:
            raise ValueError("--emulate-faults needs --emulate and a chip (--sensor NAME, not sim, no --devices)")
        if s.speedup != 1.0 and s.simulated_gyroscope:
            raise ValueError(
                "--speedup needs a simulation without a gyroscope: the wire times keep --rate, so sped-up rates "
                "would not integrate to the attitude; record the run with magnet sample and play it with magnet edge "
                "--replay FILE.csv --speed X (the recorded times are kept)"
            )


@dataclasses.dataclass(frozen=True)
class FleetOptions:
    """N simulated devices (``FleetSource``)."""

    devices: int = option(
        0, "--devices", help="with --emulate: this many simulated devices", check=_whole(0, MAX_DEVICES)
    )
    gyro: bool = option(False, "--gyro", help="with --devices: the simulated devices send a gyroscope too (gyr_rads)")

    @staticmethod
    def names_fleet(s: EdgeSettings) -> bool:
        return s.devices > 0

    @staticmethod
    def check_fleet(s: EdgeSettings) -> None:
        _check_topics(s)
        if not s.emulate:
            raise ValueError("--devices needs --emulate (a simulated fleet)")
        ChipOptions.check_simulated(s)


@dataclasses.dataclass(frozen=True)
class SimulatorOptions:
    """The simulated motion every simulated source reads (``StreamSource``, an emulated chip)."""

    trajectory_samples: int = option(
        3000, "--trajectory-samples", help="samples per run of the simulated trajectory", check=at_least(1)
    )
    speedup: float = option(
        1.0,
        "--speedup",
        help="simulated motion runs this many times faster than the wall clock (not where a gyroscope is "
        "simulated: replay a recording with --speed instead)",
        check=_in_range(0, 1000),
    )


@dataclasses.dataclass(frozen=True)
class ReplayOptions:
    """A recording at its own pace (``ReplaySource``)."""

    replay: Path | None = option(
        None,
        "--replay",
        parse=Path,
        metavar="FILE.csv",
        help="publish a recording (the columns of magnet sample, with t_s) at its own pace, then exit",
    )
    speed: float = option(
        1.0, "--speed", help="with --replay: play this many times faster than recorded", check=_in_range(0, MAX_SPEED)
    )
    mag_instance: int | None = option(
        None, "--mag", parse=int, metavar="N", help="with --replay of a flight log: the magnetometer instance"
    )

    @staticmethod
    def names_replay(s: EdgeSettings) -> bool:
        return s.replay is not None

    @staticmethod
    def check_replay(s: EdgeSettings) -> None:
        _check_topics(s)
        if s.emulate or s.devices or s.bus is not None:
            raise ValueError("--replay plays a recording: it takes no --emulate, --devices or --bus")


@dataclasses.dataclass(frozen=True)
class MavlinkOptions:
    """MAVLink vehicles (``services.edge.mavlink_source.MavlinkSource``)."""

    mavlink: str | None = url_option(
        "--mavlink",
        "read MAVLink vehicles' magnetometers: udpin:HOST:PORT, udpout:HOST:PORT, tcp:HOST:PORT or a serial "
        "device (with --baud); one device per vehicle and compass, <prefix><SYSID>-mag<N>",
    )
    baud: int = baud_option("with --mavlink and a serial device")
    device_prefix: str = option(
        "mav", "--device-prefix", help="with --mavlink: device ids start with this", check=_device_prefix
    )
    vehicle: str = option(
        "",
        "--vehicle",
        metavar="NAME",
        help="the vehicle these devices are compasses of: the compass compares the compasses of one vehicle "
        "(magnet get vehicle NAME; MAVLink vehicles are grouped by system id without it)",
        check=lambda v: None if not v else _device_id(v),
    )
    max_port_devices: int = option(
        MAX_PORT_DEVICES, "--max-port-devices", help="with --mavlink: devices (system id, compass) one connection "
        "may make; a new one beyond is dropped and counted (reads.dropped[device-limit])", check=_whole(1, 65_536)
    )  # fmt: skip
    vehicle_timeout_s: float = option(
        3.0, "--vehicle-timeout", metavar="S", check=_in_range(0, 3600, " seconds"), help="with --mavlink: a vehicle "
        "silent this long (s) makes its devices unhealthy")  # fmt: skip
    forget_after_s: float = option(
        60.0, "--forget-after", metavar="S", check=_in_range(0.1, 86_400, " seconds"), help="with --mavlink: a device "
        "silent this long (s) is forgotten: its tokens go, its place freed (reads.forgotten)")  # fmt: skip

    @staticmethod
    def names_mavlink(s: EdgeSettings) -> bool:
        return s.mavlink is not None

    @staticmethod
    def check_mavlink(s: EdgeSettings) -> None:
        if s.emulate or s.devices or s.bus is not None or s.replay is not None:
            raise ValueError("--mavlink reads vehicles: it takes no --emulate, --devices, --bus or --replay")


@dataclasses.dataclass(frozen=True)
class Ros2SourceOptions:
    """A ROS 2 robot's topics over rmw_zenoh (``services.edge.ros2_source.Ros2Source``; ``--ros2`` and its domain
    and namespace are ``EdgeSettings.ros2``)."""

    mag_topic: str | None = option(
        None,
        "--mag-topic",
        help="with --ros2, or --replay of a ROS 2 recording: the sensor_msgs/msg/MagneticField topic",
    )
    imu_topic: str | None = option(
        None, "--imu-topic", help="with --ros2: the sensor_msgs/msg/Imu topic (acceleration, rates)"
    )

    @staticmethod
    def names_ros2(s: EdgeSettings) -> bool:
        return s.ros2.enabled

    @staticmethod
    def check_ros2(s: EdgeSettings) -> None:
        if not s.mag_topic or s.emulate or s.replay or s.bus is not None:
            raise ValueError("a ROS 2 source needs --ros2 and --mag-topic, and no --emulate, --replay or --bus")


@dataclasses.dataclass(frozen=True)
class EdgeSettings(
    Ros2SourceOptions, MavlinkOptions, ReplayOptions, SimulatorOptions, FleetOptions, ChipOptions, CommonOptions
):
    """What ``magnet edge`` runs: each source's own options (``SOURCE_OPTIONS``) beside what every source takes.
    rate_hz per device; duration_s None: until stopped."""

    simulator: SimulatorSettings = EdgeSimulatorSettings()
    ros2: Ros2Settings = Ros2Settings()
    zenoh: ZenohSettings = ZenohSettings()

    def __post_init__(self) -> None:
        check_options(self)
        SOURCE_OPTIONS[self.source_kind].check(self)

    @classmethod
    def from_args(cls, args: argparse.Namespace) -> EdgeSettings:
        """The settings of the options ``add_arguments`` added, checked; ValueError naming the flag."""
        return from_args(
            cls,
            args,
            simulator=EdgeSimulatorSettings.from_args(args),
            ros2=Ros2Settings.from_args(args),
            zenoh=ZenohSettings.from_args(args),
        )

    @property
    def source_kind(self) -> SourceKind:
        """Which source the options name: the first of ``SOURCE_OPTIONS`` (in the options' precedence) whose
        options name it."""
        return next(kind for kind, source in SOURCE_OPTIONS.items() if source.named(self))

    @property
    def sensor_name(self) -> str:
        """What the status calls the sensor: the chip's name, ``sim``, ``mavlink`` or ``ros2``."""
        return {SourceKind.MAVLINK: "mavlink", SourceKind.ROS2: "ros2"}.get(self.source_kind, self.sensor)

    @property
    def location(self) -> Location | None:
        """Where the device is, sent in every raw message: --location, or the simulator's place when emulating."""
        if self.simulator.location is not None:
            return self.simulator.location
        return DEFAULT_PLACE if self.emulate else None

    @property
    def emulated_chip(self) -> bool:
        return self.emulate and not self.devices and self.sensor != SIMULATOR_SENSOR

    @property
    def simulated_gyroscope(self) -> bool:
        """The simulation sends a gyroscope: a fleet with --gyro, the simulator on a moving trajectory, or an emulated
        chip that has one."""
        if not self.emulate:
            return False
        if self.devices:
            return self.gyro
        if self.sensor == SIMULATOR_SENSOR:
            return self.simulator.trajectory.moving
        return has_gyroscope(self.sensor)


def _check_topics(s: EdgeSettings) -> None:
    if s.imu_topic or (s.mag_topic and s.replay is None):
        raise ValueError("--mag-topic and --imu-topic need --ros2 (or --mag-topic: the topic of a --replay bag)")


@dataclasses.dataclass(frozen=True)
class SourceOptions:
    """A kind of source's own options: whether the settings name it (``named``) and what it refuses or needs of
    them (``check``, run after every value is checked)."""

    named: Callable[[EdgeSettings], bool]
    check: Callable[[EdgeSettings], None]


#: each kind of source and its options, in the options' precedence (the first named is the source; its order is
#: that of ``SourceKind``): the one table of which options each source declares
SOURCE_OPTIONS: dict[SourceKind, SourceOptions] = {
    SourceKind.MAVLINK: SourceOptions(MavlinkOptions.names_mavlink, MavlinkOptions.check_mavlink),
    SourceKind.ROS2: SourceOptions(Ros2SourceOptions.names_ros2, Ros2SourceOptions.check_ros2),
    SourceKind.REPLAY: SourceOptions(ReplayOptions.names_replay, ReplayOptions.check_replay),
    SourceKind.FLEET: SourceOptions(FleetOptions.names_fleet, FleetOptions.check_fleet),
    SourceKind.SIMULATOR: SourceOptions(ChipOptions.names_simulator, ChipOptions.check_simulated),
    SourceKind.CHIP: SourceOptions(ChipOptions.names_chip, ChipOptions.check_chip),
}


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """``magnet edge``'s options: its settings' fields, the simulator's, ROS 2's and Zenoh's."""
    add_options(parser, EdgeSettings)
    add_simulator_arguments(parser, EdgeSimulatorSettings)
    add_ros2_arguments(parser, ROS2_WHAT)
    add_zenoh_arguments(parser)
