"""Options and settings of ``magnet compass``: where it is (WMM), smoothing, name, devices, shard, trusted keys,
each declared once (``services.common.options``)."""

from __future__ import annotations

import argparse
import dataclasses
from pathlib import Path
from typing import Any

from magnet import signing
from magnet.compass.core import DEFAULT_MAX_DEVICES, CoreSettings, window_problem
from magnet.drift import DEFAULT_DRIFT, DriftSettings
from magnet.earth.geomag import earth_field
from magnet.earth.location import Location
from magnet.fleet.places import PlaceEntry
from magnet.shard import EVERY_DEVICE, Shard
from services.common.options import add_options, at_least, check_options, from_args, option
from services.common.places_options import add_drift_arguments, add_fleet_argument, drift_from_args, read_fleet
from services.common.ros2_options import Ros2Settings, add_ros2_arguments
from services.common.zenoh_session import ZenohSettings, add_zenoh_arguments

#: devices with ROS 2 topics at most, by default (``--ros2-max-devices``): each is two publishers and two liveliness
#: tokens, declared in the compass's loop; a flood of 12,000 new ids once held the loop for minutes
ROS2_MAX_DEVICES = 256


def _date_problem(value: Any) -> str | None:
    """A date the World Magnetic Model covers (or None: each day's own)."""
    if value is None:
        return None
    try:
        earth_field(0.0, 0.0, 0.0, value)
    except ValueError as exc:
        return f"is not a usable date ({exc})"
    return None


@dataclasses.dataclass(frozen=True)
class CompassSettings:
    """Everything ``magnet compass`` runs with: where it is (the WMM's place and date), the smoothing window
    (headings), its name, the devices it serves (a key expression chunk), the state bound, the trusted keys, the
    shard; the places file's entries, the drift thresholds and the Zenoh and ROS 2 options."""

    location: Location | None = option(
        None,
        "--location",
        parse=Location.parse,
        help="LAT,LON[,ALT_M] for the WMM declination and expected field "
        "(without it: declination 0, no field/dip disturbance check)",
    )
    date: str | None = option(None, "--date", check=_date_problem, help="date for the WMM (YYYY-MM-DD; default today)")
    window: int = option(1, "--window", check=window_problem, help="circular sliding mean over N headings")
    name: str = option("compass", "--name", help="service name for liveliness and status")
    devices: str = option(
        "*",
        "--devices",
        show_default=False,
        help="key expression of the devices this instance serves (default *, all); e.g. 'line-1-*'",
    )
    max_devices: int = option(
        DEFAULT_MAX_DEVICES,
        "--max-devices",
        check=at_least(1),
        help="devices whose state (calibration, smoothing, keys) is kept at most; beyond, the least "
        "recently seen is forgotten",
    )
    ros2_max_devices: int = option(
        ROS2_MAX_DEVICES,
        "--ros2-max-devices",
        check=at_least(1),
        help="with --ros2: devices with ROS 2 topics at most (a device gets them once it has sent 3 batches); a new "
        "device beyond takes the slot of one silent for a while, else its samples stay off ROS 2 (counted: "
        "dropped[ros2:device-limit])",
    )
    trust: tuple[Path, ...] = option(
        (),
        "--trust",
        repeat=True,
        parse=Path,
        metavar="FILE.pub",
        help="apply only calibrations signed by this public key (repeatable; `magnet keys` makes "
        "them). Without it, unsigned calibrations are applied too",
    )
    shard: Shard = option(
        EVERY_DEVICE,
        "--shard",
        parse=Shard.parse,
        metavar="K/N",
        show_default=False,
        help="serve only the devices of shard K of N (0 <= K < N; see magnet.shard: sha256 of the "
        "device id, first 8 bytes, mod N); default 0/1, every device",
    )
    places: tuple[PlaceEntry, ...] = ()  # the --fleet file's entries
    drift: DriftSettings | None = DEFAULT_DRIFT
    zenoh: ZenohSettings = ZenohSettings()
    ros2: Ros2Settings = Ros2Settings()

    def __post_init__(self) -> None:
        check_options(self)

    @property
    def core(self) -> CoreSettings:
        return CoreSettings(self.window, self.max_devices, self.shard, self.drift)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    add_options(parser, CompassSettings)
    add_fleet_argument(parser)
    add_drift_arguments(parser)
    add_ros2_arguments(parser, "also publish each device's field, attitude and diagnostics as ROS 2 topics (rmw_zenoh)")
    add_zenoh_arguments(parser)


def settings_from_args(args: argparse.Namespace) -> CompassSettings:
    return from_args(
        CompassSettings,
        args,
        places=tuple(read_fleet(args.fleet).values()),
        drift=drift_from_args(args),
        zenoh=ZenohSettings.from_args(args),
        ros2=Ros2Settings.from_args(args),
    )


def load_trusted_keys(paths: tuple[Path, ...] | list[Path]) -> signing.TrustedKeys:
    """The public keys of ``--trust`` files; OSError/ValueError naming a file that cannot be used."""
    return signing.TrustedKeys([signing.load_public_key(path.read_bytes(), str(path)) for path in paths])


#: the compass puts a drain's headings at once (thousands of messages): room for them in each link's queue (16
#: batches of 64 kB, Zenoh's most; its default is 2), and up to 20 ms for a busy machine's sending thread to make room
#: before a heading is dropped (default 1 ms). A subscriber that stays slow still loses headings, never the compass's
#: time for long. A --config file replaces these.
ZENOH_DEFAULTS = {
    "transport/link/rx/max_message_size": str(8 * 1024 * 1024),  # no raw message may be larger than 4 MB anyway
    "transport/link/tx/queue/size/data": "16",
    "transport/link/tx/queue/congestion_control/drop/wait_before_drop": "20000",
}
