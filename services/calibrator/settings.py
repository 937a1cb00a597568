"""``magnet calibrator`` options and settings: what it fits with, where it stores, which devices it serves, its
signing key.
"""

from __future__ import annotations

import argparse
import dataclasses
import logging
import os
from pathlib import Path

from magnet import signing
from magnet.calibration import Method
from magnet.compass.places import Places
from magnet.geomag import earth_field
from magnet.place import Location
from magnet.shard import EVERY_DEVICE, Shard
from services.calibrator.intake import DEFAULT_ENROL_RATE, DEFAULT_MAX_QUEUE
from services.common.places_options import add_fleet_argument, read_fleet
from services.common.zenoh_session import ZenohSettings, add_zenoh_arguments

log = logging.getLogger("magnet.calibrator")

DEFAULT_MAX_DEVICES = 10_000


def default_db_path() -> Path:
    base = Path(os.environ.get("XDG_DATA_HOME", Path.home() / ".local" / "share"))
    return base / "magnet" / "calibrations.db"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--db", type=Path, default=None, help=f"SQLite file (default {default_db_path()})")
    parser.add_argument(
        "--method",
        default="ellipsoid",
        help="fit method for automatic calibration (default ellipsoid; sessions may choose another)",
    )
    parser.add_argument("--location", help="LAT,LON[,ALT_M]: scale fits to the WMM field strength there")
    parser.add_argument("--field-ut", type=float, help="expected field strength in uT (instead of --location)")
    parser.add_argument(
        "--min-coverage", type=float, default=0.8, help="sphere coverage before an automatic fit is tried (default 0.8)"
    )
    parser.add_argument("--min-samples", type=int, default=150, help="kept samples before a fit (default 150)")
    parser.add_argument("--max-samples", type=int, default=1500, help="kept samples per device at most")
    parser.add_argument("--no-auto", action="store_true", help="calibrate only in operator sessions")
    parser.add_argument("--name", default="calibrator", help="service name for liveliness and status")
    parser.add_argument("--devices", default="*", help="key expression of the devices served (default *)")
    parser.add_argument(
        "--max-devices",
        type=int,
        default=DEFAULT_MAX_DEVICES,
        help="devices collected at once and kept in the fleet book at most; beyond, the least recently seen are "
        f"dropped (sessions stay) (default {DEFAULT_MAX_DEVICES})",
    )
    add_fleet_argument(parser)
    parser.add_argument(
        "--signing-key",
        type=Path,
        metavar="FILE.key",
        help="sign every calibration it serves with this Ed25519 private key (`magnet keys`); "
        "compasses started with --trust FILE.pub apply only those",
    )
    parser.add_argument(
        "--shard",
        default="0/1",
        metavar="K/N",
        help="collect, fit, store and answer only for the devices of shard K of N (0 <= K < N; see "
        "magnet.shard); default 0/1, every device",
    )
    parser.add_argument(
        "--enrol-rate",
        type=float,
        default=DEFAULT_ENROL_RATE,
        help="new device ids taken on per second at most (10 s of them at once); beyond, their samples are dropped "
        f"and counted in status dropped[raw:enrol-rate] (default {DEFAULT_ENROL_RATE:g})",
    )
    parser.add_argument(
        "--max-queue",
        type=int,
        default=DEFAULT_MAX_QUEUE,
        help="raw messages waiting to be processed at most; beyond, dropped and counted in status "
        f"dropped[raw:queue-full] (default {DEFAULT_MAX_QUEUE})",
    )
    add_zenoh_arguments(parser)


@dataclasses.dataclass(frozen=True)
class CalibratorSettings:
    """How the calibrator fits: method, expected |B| (uT or None), coverage and sample counts, automatic or not."""

    method: str = "ellipsoid"
    field_ut: float | None = None
    min_coverage: float = 0.8
    min_samples: int = 150
    max_samples: int = 1500
    auto: bool = True
    max_devices: int = DEFAULT_MAX_DEVICES

    def __post_init__(self) -> None:
        Method.parse(self.method)
        if not 0 <= self.min_coverage <= 1:
            raise ValueError(f"--min-coverage must be a fraction in [0, 1], got {self.min_coverage}")
        if not 30 <= self.min_samples <= self.max_samples:
            raise ValueError(f"need 30 <= --min-samples <= --max-samples, got {self.min_samples}, {self.max_samples}")
        if self.field_ut is not None and not 1 <= self.field_ut <= 1000:
            raise ValueError(f"--field-ut must be a field strength in uT (1..1000), got {self.field_ut}")
        if isinstance(self.max_devices, bool) or not isinstance(self.max_devices, int) or self.max_devices < 1:
            raise ValueError(f"--max-devices must be a whole number >= 1, got {self.max_devices}")


@dataclasses.dataclass(frozen=True)
class ServiceSettings:
    """Everything ``magnet calibrator`` runs with: the fit settings, the database, its name, the devices it serves
    (a key expression chunk) and the Zenoh options."""

    fitting: CalibratorSettings
    db: Path
    name: str = "calibrator"
    devices: str = "*"
    zenoh: ZenohSettings = ZenohSettings()
    signing_key: Path | None = None
    places: Places | None = None  # --fleet file and --location: each device's expected field
    shard: Shard = EVERY_DEVICE
    enrol_rate: float = DEFAULT_ENROL_RATE  # new device ids per second (services.calibrator.intake)
    max_queue: int = DEFAULT_MAX_QUEUE  # raw messages waiting at most

    def __post_init__(self) -> None:
        if not (self.enrol_rate > 0 and self.enrol_rate < float("inf")):
            raise ValueError(f"--enrol-rate must be a positive number of new devices per second, got {self.enrol_rate}")
        if isinstance(self.max_queue, bool) or not isinstance(self.max_queue, int) or self.max_queue < 1:
            raise ValueError(f"--max-queue must be a whole number >= 1, got {self.max_queue}")


def settings_from_args(args: argparse.Namespace) -> ServiceSettings:
    field_ut = args.field_ut
    if field_ut is None and args.location:
        field_ut = earth_field(*Location.parse(args.location).as_tuple()).total_ut
    fitting = CalibratorSettings(
        method=args.method,
        field_ut=field_ut,
        min_coverage=args.min_coverage,
        min_samples=args.min_samples,
        max_samples=args.max_samples,
        auto=not args.no_auto,
        max_devices=args.max_devices,
    )
    location = Location.parse(args.location) if args.location else None
    places = Places(read_fleet(args.fleet), location, max_reported=fitting.max_devices)
    return ServiceSettings(
        fitting,
        args.db or default_db_path(),
        args.name,
        args.devices,
        ZenohSettings.from_args(args),
        args.signing_key,
        places,
        Shard.parse(args.shard),
        args.enrol_rate,
        args.max_queue,
    )


def load_signer(path: Path | None) -> signing.Signer | None:
    """The signer of ``--signing-key`` (None without one); OSError/ValueError naming a file that cannot be used."""
    if path is None:
        return None
    if path.stat().st_mode & 0o077:
        log.warning("signing key %s is readable by others: chmod 600 it", path)
    return signing.Signer(signing.load_private_key(path.read_bytes(), str(path)))
