"""``magnet edge``'s options and the typed, checked settings built from them (``EdgeSettings.from_args``)."""

from __future__ import annotations

import argparse
import dataclasses
from pathlib import Path

from magnet import wire
from magnet.drivers import SENSORS, has_gyroscope
from magnet.place import Location
from magnet.replay import MAX_SPEED
from services.common import sim_options
from services.common.mavlink_options import add_mavlink_url_arguments
from services.common.ros2_options import Ros2Settings, add_ros2_arguments
from services.common.zenoh_session import ZenohSettings, add_zenoh_arguments

SIMULATOR_SENSOR = "sim"
MAX_RATE_HZ = 100_000.0
MAX_DEVICES = 100_000


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--device", default="dev", help="device id (one key chunk); a fleet uses <ID>-000, ...")
    parser.add_argument(
        "--sensor", default=SIMULATOR_SENSOR, help=f"chip name ({', '.join(SENSORS)}) or 'sim' for the simulator alone"
    )
    parser.add_argument("--bus", type=int, help="I2C bus number of a real chip (/dev/i2c-N)")
    parser.add_argument("--address", type=lambda s: int(s, 0), help="I2C address of a real chip (e.g. 0x1e)")
    parser.add_argument("--emulate", action="store_true", help="emulate the chip (or the fleet) instead of a bus")
    parser.add_argument("--devices", type=int, default=0, help="with --emulate: this many simulated devices")
    parser.add_argument("--rate", type=float, default=50.0, help="samples per second per device (default 50)")
    parser.add_argument("--batch", type=int, default=10, help="samples per message (default 10)")
    parser.add_argument("--duration", type=float, help="stop after this many seconds")
    parser.add_argument(
        "--gyro", action="store_true", help="with --devices: the simulated devices send a gyroscope too (gyr_rads)"
    )
    parser.add_argument(
        "--wire",
        type=int,
        choices=wire.VERSIONS,
        default=wire.BINARY_ARRAYS_VERSION,
        help="message version: 2 binary arrays (default), 1 lists of numbers for old subscribers",
    )
    sim_options.add_simulator_arguments(parser, seed=1, noise_ut=0.3)
    parser.add_argument(
        "--trajectory-samples",
        type=int,
        default=3000,
        help="samples per run of the simulated trajectory (default 3000)",
    )
    parser.add_argument(
        "--speedup",
        type=float,
        default=1.0,
        help="simulated motion runs this many times faster than the wall clock (default 1; not where a gyroscope is "
        "simulated: replay a recording with --speed instead)",
    )
    parser.add_argument(
        "--emulate-faults",
        type=float,
        default=0.0,
        metavar="P",
        help="with --emulate and a chip, for tests: each I2C transfer after set-up fails with EIO "
        "with probability P (1: a dead bus)",
    )
    parser.add_argument(
        "--replay",
        type=Path,
        metavar="FILE.csv",
        help="publish a recording (the columns of magnet sample, with t_s) at its own pace, then exit",
    )
    parser.add_argument(
        "--speed", type=float, default=1.0, help="with --replay: play this many times faster than recorded (default 1)"
    )
    add_mavlink_arguments(parser)
    add_ros2_arguments(parser, "read a ROS 2 robot's MagneticField (and Imu) topics over rmw_zenoh (--mag-topic)")
    parser.add_argument(
        "--mag-topic", help="with --ros2, or --replay of a ROS 2 recording: the sensor_msgs/msg/MagneticField topic"
    )
    parser.add_argument(
        "--mag",
        type=int,
        metavar="N",
        dest="mag_instance",
        help="with --replay of a flight log: the magnetometer instance",
    )
    parser.add_argument("--imu-topic", help="with --ros2: the sensor_msgs/msg/Imu topic (acceleration, rates)")
    add_zenoh_arguments(parser)


def add_mavlink_arguments(parser: argparse.ArgumentParser) -> None:
    """The options of a MAVLink source (``services.edge.mavlink_source``)."""
    add_mavlink_url_arguments(
        parser,
        "--mavlink",
        "read MAVLink vehicles' magnetometers: udpin:HOST:PORT, udpout:HOST:PORT, tcp:HOST:PORT or a serial "
        "device (with --baud); one device per vehicle and compass, <prefix><SYSID>-mag<N>",
        "with --mavlink and a serial device (default 57600)",
    )
    parser.add_argument("--device-prefix", default="mav", help="with --mavlink: device ids start with this (mav)")
    parser.add_argument(
        "--vehicle-timeout",
        type=float,
        default=3.0,
        metavar="S",
        help="with --mavlink: a vehicle silent this long makes its devices unhealthy (default 3 s)",
    )


@dataclasses.dataclass(frozen=True)
class EdgeSettings:
    """What ``magnet edge`` runs, checked in one place. rate_hz per device; duration_s None: until stopped."""

    device: str = "dev"
    sensor: str = SIMULATOR_SENSOR
    rate_hz: float = 50.0
    batch: int = 10
    duration_s: float | None = None
    bus: int | None = None
    address: int | None = None
    emulate: bool = False
    devices: int = 0
    trajectory_samples: int = 3000
    speedup: float = 1.0
    emulate_faults: float = 0.0
    wire_version: int = wire.BINARY_ARRAYS_VERSION
    gyro: bool = False
    replay: Path | None = None
    speed: float = 1.0
    simulator: sim_options.SimulatorSettings = dataclasses.field(default_factory=sim_options.SimulatorSettings)
    zenoh: ZenohSettings = dataclasses.field(default_factory=ZenohSettings)
    #: where the device is, sent in every raw message: --location, or the simulator's place when emulating
    location: Location | None = None
    mavlink: str | None = None
    baud: int = 57600
    device_prefix: str = "mav"
    vehicle_timeout_s: float = 3.0
    ros2: Ros2Settings = Ros2Settings()
    mag_topic: str | None = None
    imu_topic: str | None = None
    mag_instance: int | None = None

    def __post_init__(self) -> None:
        wire.validate_device_id(self.device)
        if not 0 < self.rate_hz <= MAX_RATE_HZ:
            raise ValueError(f"--rate must be in (0, {MAX_RATE_HZ:g}] Hz, got {self.rate_hz}")
        if not 1 <= self.batch <= wire.MAX_BATCH_SAMPLES:
            raise ValueError(f"--batch must be 1..{wire.MAX_BATCH_SAMPLES}, got {self.batch}")
        if self.duration_s is not None and not self.duration_s >= 0:
            raise ValueError(f"--duration must be >= 0 seconds, got {self.duration_s}")
        if not 0 < self.speedup <= 1000:
            raise ValueError(f"--speedup must be in (0, 1000], got {self.speedup}")
        if self.trajectory_samples < 1:
            raise ValueError(f"--trajectory-samples must be >= 1, got {self.trajectory_samples}")
        if self.wire_version not in wire.VERSIONS:
            raise ValueError(f"--wire must be one of {', '.join(map(str, wire.VERSIONS))}, got {self.wire_version}")
        self._check_source()

    def _check_source(self) -> None:
        if not 0 < self.speed <= MAX_SPEED:
            raise ValueError(f"--speed must be in (0, {MAX_SPEED:g}], got {self.speed}")
        if self.mavlink is not None:
            self._check_mavlink()
            return
        if self.ros2.enabled:
            if not self.mag_topic or self.emulate or self.replay or self.bus is not None:
                raise ValueError("a ROS 2 source needs --ros2 and --mag-topic, and no --emulate, --replay or --bus")
            return
        if self.imu_topic or (self.mag_topic and self.replay is None):
            raise ValueError("--mag-topic and --imu-topic need --ros2 (or --mag-topic: the topic of a --replay bag)")
        if self.replay is not None:
            if self.emulate or self.devices or self.bus is not None:
                raise ValueError("--replay plays a recording: it takes no --emulate, --devices or --bus")
            return
        if not 0 <= self.devices <= MAX_DEVICES:
            raise ValueError(f"--devices must be 0..{MAX_DEVICES}, got {self.devices}")
        if self.devices and not self.emulate:
            raise ValueError("--devices needs --emulate (a simulated fleet)")
        if not self.emulate and self.bus is None:
            raise ValueError("a real sensor needs --bus N (or --emulate)")
        if not 0 <= self.emulate_faults <= 1:
            raise ValueError(f"--emulate-faults must be a probability in [0, 1], got {self.emulate_faults}")
        if self.emulate_faults and not self.emulated_chip:
            raise ValueError("--emulate-faults needs --emulate and a chip (--sensor NAME, not sim, no --devices)")
        if self.speedup != 1.0 and self.simulated_gyroscope:
            raise ValueError(
                "--speedup needs a simulation without a gyroscope: the wire times keep --rate, so sped-up rates would "
                "not integrate to the attitude; record the run with magnet sample and play it with magnet edge "
                "--replay FILE.csv --speed X (the recorded times are kept)"
            )

    def _check_mavlink(self) -> None:
        if self.emulate or self.devices or self.bus is not None or self.replay is not None:
            raise ValueError("--mavlink reads vehicles: it takes no --emulate, --devices, --bus or --replay")
        if not self.mavlink:
            raise ValueError("--mavlink needs a URL: udpin:HOST:PORT, udpout:HOST:PORT, tcp:HOST:PORT or a device")
        _check_network_url(self.mavlink)
        wire.validate_device_id(f"{self.device_prefix}1-mag0")
        if not 0 < self.vehicle_timeout_s <= 3600:
            raise ValueError(f"--vehicle-timeout must be in (0, 3600] seconds, got {self.vehicle_timeout_s}")
        if not 50 <= self.baud <= 10_000_000:
            raise ValueError(f"--baud must be 50..10000000, got {self.baud}")

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

    @classmethod
    def from_args(cls, args: argparse.Namespace) -> EdgeSettings:
        return cls(
            device=args.device,
            sensor="ros2" if getattr(args, "ros2", False) else args.sensor,
            rate_hz=float(args.rate),
            batch=int(args.batch),
            duration_s=args.duration,
            bus=args.bus,
            address=args.address,
            emulate=bool(args.emulate),
            devices=int(args.devices),
            trajectory_samples=int(args.trajectory_samples),
            speedup=float(args.speedup),
            emulate_faults=float(args.emulate_faults),
            replay=args.replay,
            speed=float(args.speed),
            wire_version=int(getattr(args, "wire", wire.BINARY_ARRAYS_VERSION)),
            gyro=bool(getattr(args, "gyro", False)),
            simulator=sim_options.SimulatorSettings.from_args(args),
            zenoh=ZenohSettings.from_args(args),
            location=_location(args),
            mavlink=getattr(args, "mavlink", None),
            baud=int(getattr(args, "baud", 57600)),
            device_prefix=getattr(args, "device_prefix", "mav"),
            vehicle_timeout_s=float(getattr(args, "vehicle_timeout", 3.0)),
            ros2=Ros2Settings.from_args(args),
            mag_topic=args.mag_topic,
            imu_topic=args.imu_topic,
            mag_instance=args.mag_instance,
        )


#: pymavlink's network links: KIND:HOST:PORT (anything else is a serial device path)
NETWORK_LINKS = ("udpin", "udpout", "udp", "udpbcast", "tcp", "tcpin")


def _check_network_url(url: str) -> None:
    """ValueError when a network MAVLink URL has no HOST:PORT with a port in 1..65535."""
    kind, _, rest = url.partition(":")
    if kind not in NETWORK_LINKS:
        return
    host, _, port = rest.rpartition(":")
    if not host or not port.isdigit() or not 1 <= int(port) <= 65535:
        raise ValueError(f"--mavlink {url}: expected {kind}:HOST:PORT with a port in 1..65535")


def _location(args: argparse.Namespace) -> Location | None:
    """The place the edge reports: --location when given, else the simulator's (emulated devices), else None."""
    if args.location:
        return Location.parse(args.location)
    return Location.parse(sim_options.DEFAULT_LOCATION) if args.emulate else None
