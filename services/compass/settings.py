"""Options and settings of ``magnet compass``: where it is (WMM), smoothing, name, devices, shard, trusted keys."""

from __future__ import annotations

import argparse
import dataclasses
from pathlib import Path
from typing import Any

from magnet import signing
from magnet.compass import Earth
from magnet.drift import DEFAULT_DRIFT, DriftSettings
from magnet.place import Location
from magnet.shard import EVERY_DEVICE, Shard
from services.common.fleet_options import add_drift_arguments, add_fleet_argument, drift_from_args, read_fleet
from services.common.ros2_options import Ros2Settings, add_ros2_arguments
from services.common.zenoh_session import ZenohSettings, add_zenoh_arguments

DEFAULT_MAX_DEVICES = 10_000


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--location",
        help="LAT,LON[,ALT_M] for the WMM declination and expected field "
        "(without it: declination 0, no field/dip disturbance check)",
    )
    parser.add_argument("--date", help="date for the WMM (YYYY-MM-DD; default today)")
    parser.add_argument("--window", type=int, default=1, help="circular sliding mean over N headings (default 1)")
    parser.add_argument("--name", default="compass", help="service name for liveliness and status (default compass)")
    parser.add_argument(
        "--devices",
        default="*",
        help="key expression of the devices this instance serves (default *, all); e.g. 'line-1-*'",
    )
    parser.add_argument(
        "--max-devices",
        type=int,
        default=DEFAULT_MAX_DEVICES,
        help="devices whose state (calibration, smoothing, keys) is kept at most; beyond, the least "
        f"recently seen is forgotten (default {DEFAULT_MAX_DEVICES})",
    )
    parser.add_argument(
        "--trust",
        action="append",
        default=[],
        type=Path,
        metavar="FILE.pub",
        help="apply only calibrations signed by this public key (repeatable; `magnet keys` makes "
        "them). Without it, unsigned calibrations are applied too",
    )
    parser.add_argument(
        "--shard",
        default="0/1",
        metavar="K/N",
        help="serve only the devices of shard K of N (0 <= K < N; see magnet.shard: sha256 of the "
        "device id, first 8 bytes, mod N); default 0/1, every device",
    )
    add_fleet_argument(parser)
    add_drift_arguments(parser)
    add_ros2_arguments(parser, "also publish each device's field, attitude and diagnostics as ROS 2 topics (rmw_zenoh)")
    add_zenoh_arguments(parser)


@dataclasses.dataclass(frozen=True)
class CompassSettings:
    """Everything ``magnet compass`` runs with: what it expects where it is, the smoothing window (headings), its
    name, the devices it serves (a key expression chunk) and the Zenoh options."""

    earth: Earth = Earth()
    window: int = 1
    name: str = "compass"
    devices: str = "*"
    zenoh: ZenohSettings = ZenohSettings()
    trust: tuple[Path, ...] = ()
    max_devices: int = DEFAULT_MAX_DEVICES
    places: tuple[Location | None, str | None, dict[str, Any]] = (None, None, {})  # default, date, fleet file
    drift: DriftSettings | None = DEFAULT_DRIFT
    shard: Shard = EVERY_DEVICE
    ros2: Ros2Settings = Ros2Settings()

    def __post_init__(self) -> None:
        if isinstance(self.window, bool) or not isinstance(self.window, int) or self.window < 1:
            raise ValueError(f"--window must be >= 1, got {self.window}")


def settings_from_args(args: argparse.Namespace) -> CompassSettings:
    default = Location.parse(args.location) if args.location else None
    return CompassSettings(
        Earth.from_args(args.location, args.date),
        args.window,
        args.name,
        args.devices,
        ZenohSettings.from_args(args),
        tuple(args.trust),
        max_devices=args.max_devices,
        places=(default, args.date, read_fleet(args.fleet)),
        drift=drift_from_args(args),
        shard=Shard.parse(args.shard),
        ros2=Ros2Settings.from_args(args),
    )


def load_trusted_keys(paths: tuple[Path, ...] | list[Path]) -> signing.TrustedKeys:
    """The public keys of ``--trust`` files; OSError/ValueError naming a file that cannot be used."""
    return signing.TrustedKeys([signing.load_public_key(path.read_bytes(), str(path)) for path in paths])
