"""``magnet calibrator`` settings, declared once (``services.common.options``): how it fits (``CalibratorSettings``)
and how it runs (``ServiceSettings``: where it stores, which devices it serves, its signing key, its bounds). Every
field that is an option carries its flag, default, help and check; ``add_arguments`` builds the options from them
and ``settings_from_args`` reads them back, checked.

This module is the calibrator's one user of the places modules (the fleet file, the model field at a place): the
settings hold the fleet file's entries, immutable, and ``make_places`` builds the mutable ``Places`` a service keeps.
"""

from __future__ import annotations

import argparse
import dataclasses
import logging
import os
from pathlib import Path
from typing import Any

from magnet import signing
from magnet.calibration.choose import AUTO, CHOICES, parse_choice
from magnet.calibrator.refresh import MODES
from magnet.calibrator.settings import DEFAULT_MAX_DEVICES as DEFAULT_MAX_DEVICES  # the option's default, named here
from magnet.earth.geomag import earth_field
from magnet.earth.location import Location
from magnet.fleet.places import PlaceEntry
from magnet.fleet.places import Places as Places  # the roster's type, named here with the rest of the places modules
from magnet.shard import EVERY_DEVICE, Shard
from services.calibrator.intake import DEFAULT_ENROL_RATE, DEFAULT_MAX_QUEUE
from services.common.options import add_options, at_least, check_options, from_args, option, positive, within
from services.common.places_options import add_fleet_argument, read_fleet
from services.common.stores import StoreLocation, parse_db
from services.common.zenoh_session import ZenohSettings, add_zenoh_arguments

log = logging.getLogger("magnet.calibrator")

#: fewest samples kept before a fit (and the least --max-samples may be)
MIN_SAMPLES = 30


def default_db_path() -> Path:
    base = Path(os.environ.get("XDG_DATA_HOME", Path.home() / ".local" / "share"))
    return base / "magnet" / "calibrations.db"


def _method(value: Any) -> str | None:
    try:
        parse_choice(value)
    except ValueError:
        return f"must be one of {', '.join(CHOICES)}"
    return None


@dataclasses.dataclass(frozen=True)
class CalibratorSettings:
    """How the calibrator fits: method, expected |B| (``--field-ut``, else the model's at ``--location``, else None:
    the fit's own), coverage and sample counts, automatic or not, devices collected at once. What the core reads of
    them is ``magnet.calibrator.settings.Settings``."""

    method: str = option(
        AUTO,
        "--method",
        check=_method,
        help="fit method for automatic calibration (sessions may choose another); auto: gyro-ellipsoid or ellipsoid, "
        "whichever the gate finds better, ellipsoid for a device without a gyroscope",
    )
    location: Location | None = option(
        None,
        "--location",
        parse=Location.parse,
        metavar="LAT,LON[,ALT_M]",
        help="scale fits to the WMM field strength there (and the place of devices that say nothing of theirs)",
    )
    field_ut: float | None = option(
        None,
        "--field-ut",
        parse=float,
        check=within(1, 1000, "a field strength in uT"),
        help="expected field strength in uT (instead of --location)",
    )
    min_coverage: float = option(
        0.8,
        "--min-coverage",
        check=within(0, 1, "a fraction"),
        help="sphere coverage before an automatic fit is tried",
    )
    min_samples: int = option(150, "--min-samples", check=at_least(MIN_SAMPLES), help="kept samples before a fit")
    max_samples: int = option(
        1500, "--max-samples", check=at_least(MIN_SAMPLES), help="kept samples per device at most"
    )
    auto: bool = option(True, "--auto", negate="--no-auto", help="calibrate only in operator sessions")
    recalibrate: str = option(
        "auto",
        "--recalibrate",
        choices=MODES,
        help="after a device's first record, keep fitting it from normal use: auto commits a record that makes "
        "held-out heading consistency better than the one in force by the margin, propose opens a session for a "
        "person to commit it, off stops after the first record",
    )
    max_devices: int = option(
        DEFAULT_MAX_DEVICES,
        "--max-devices",
        check=at_least(1),
        help="devices collected at once and kept in the roster at most; beyond, the least recently seen are dropped "
        "(sessions stay)",
    )
    expected_field_ut: float | None = dataclasses.field(init=False, default=None)  # --field-ut, or at --location

    def __post_init__(self) -> None:
        check_options(self)
        if self.min_samples > self.max_samples:
            raise ValueError(
                f"need {MIN_SAMPLES} <= --min-samples <= --max-samples, got {self.min_samples}, {self.max_samples}"
            )
        expected = self.field_ut
        if expected is None and self.location is not None:
            location = self.location
            expected = earth_field(location.lat_deg, location.lon_deg, location.alt_m).total_ut
        object.__setattr__(self, "expected_field_ut", expected)


@dataclasses.dataclass(frozen=True)
class ServiceSettings:
    """Everything ``magnet calibrator`` runs with: the fit settings, the database, its name, the devices it serves
    (a key expression chunk), the fleet file's entries and the Zenoh options."""

    fitting: CalibratorSettings = CalibratorSettings()
    db: StoreLocation | None = option(
        None,
        "--db",
        parse=parse_db,
        show_default=False,
        metavar="FILE.sqlite3|postgresql://USER@HOST:PORT/DB",
        help="where calibrations are stored: a SQLite file (one host) or a PostgreSQL database that calibrators on "
        f"several hosts share (docs/calibrator.md) (default {default_db_path()})",
    )
    name: str = option("calibrator", "--name", help="service name for liveliness and status")
    devices: str = option("*", "--devices", help="key expression of the devices served")
    signing_key: Path | None = option(
        None,
        "--signing-key",
        parse=Path,
        metavar="FILE.key",
        help="sign every calibration it serves with this Ed25519 private key (`magnet keys`); compasses started "
        "with --trust FILE.pub apply only those",
    )
    shard: Shard = option(
        EVERY_DEVICE,
        "--shard",
        parse=Shard.parse,
        metavar="K/N",
        help="collect, fit, store and answer only for the devices of shard K of N (0 <= K < N; see magnet.shard); "
        "0/1 is every device",
    )
    enrol_rate: float = option(
        DEFAULT_ENROL_RATE,
        "--enrol-rate",
        check=positive,
        help="new device ids taken on per second at most (10 s of them at once); beyond, their samples are dropped "
        "and counted in status dropped[raw:enrol-rate]",
    )
    max_queue: int = option(
        DEFAULT_MAX_QUEUE,
        "--max-queue",
        check=at_least(1),
        help="raw messages waiting to be processed at most; beyond, dropped and counted in status "
        "dropped[raw:queue-full]",
    )
    fleet: tuple[PlaceEntry, ...] = ()  # --fleet FILE.json5: each device's place and notes
    zenoh: ZenohSettings = ZenohSettings()

    def __post_init__(self) -> None:
        check_options(self)

    @property
    def db_path(self) -> StoreLocation:
        """--db, else the default SQLite file in the user's data directory."""
        return self.db if self.db is not None else default_db_path()


def add_arguments(parser: argparse.ArgumentParser) -> None:
    add_options(parser, CalibratorSettings)
    add_options(parser, ServiceSettings)
    add_fleet_argument(parser)
    add_zenoh_arguments(parser)


def settings_from_args(args: argparse.Namespace) -> ServiceSettings:
    """The checked settings of the parsed options; ValueError naming the option that is wrong."""
    return from_args(
        ServiceSettings,
        args,
        fitting=from_args(CalibratorSettings, args),
        fleet=tuple(read_fleet(args.fleet).values()),
        zenoh=ZenohSettings.from_args(args),
    )


def make_places(
    fleet: tuple[PlaceEntry, ...] = (), default: Location | None = None, max_devices: int = DEFAULT_MAX_DEVICES
) -> Places:
    """Each device's place and expected field: reported, else its fleet-file entry's, else ``default``; reported
    places remembered for at most ``max_devices`` devices."""
    return Places({entry.device: entry for entry in fleet}, default, max_reported=max_devices)


def load_signer(path: Path | None) -> signing.Signer | None:
    """The signer of ``--signing-key`` (None without one); OSError/ValueError naming a file that cannot be used."""
    if path is None:
        return None
    if path.stat().st_mode & 0o077:
        log.warning("signing key %s is readable by others: chmod 600 it", path)
    return signing.Signer(signing.load_private_key(path.read_bytes(), str(path)))
