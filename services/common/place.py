"""Where the device is, from the command line: ``--location`` / ``--date`` (the World Magnetic Model), ``--field-ut``
and ``--declination``; shared by ``magnet fit``, ``heading`` and ``report``."""

from __future__ import annotations

import argparse

from magnet.earth.geomag import earth_field
from magnet.earth.location import Location


def add_field_arguments(parser: argparse.ArgumentParser) -> None:
    """The options that say where the device is: shared by ``fit`` and ``heading``."""
    parser.add_argument("--location", metavar="LAT,LON[,ALT_M]", help="place, for the World Magnetic Model (WMM2025)")
    parser.add_argument("--date", metavar="YYYY-MM-DD", help="date for the World Magnetic Model (default: today)")


def location_instead_of(args: argparse.Namespace, flag: str, value: object) -> Location | None:
    """--location parsed (None when not given); ValueError when ``flag`` (the option --location replaces:
    --field-ut, --declination) was given too."""
    if value is not None and args.location:
        raise ValueError(f"give either {flag} or --location, not both")
    return Location.parse(args.location) if args.location else None


def date_needs_location(args: argparse.Namespace) -> None:
    """ValueError when --date was given without --location (the date is the World Magnetic Model's)."""
    if args.date:
        raise ValueError("--date needs --location")


def expected_field_ut(args: argparse.Namespace) -> float | None:
    """The field strength to scale to, in uT: --field-ut, or the WMM at --location, or None."""
    location = location_instead_of(args, "--field-ut", args.field_ut)
    if args.field_ut is not None:
        if not (0 < args.field_ut < 1000):
            raise ValueError(f"--field-ut {args.field_ut} is not a plausible field strength in uT (Earth: 22-67)")
        return float(args.field_ut)
    if location is not None:
        return earth_field(*location.as_tuple(), args.date).total_ut
    date_needs_location(args)
    return None


def place(args: argparse.Namespace) -> tuple[float | None, float | None]:
    """(declination deg, expected field uT) from --declination or --location/--date, each None when not given."""
    declination = getattr(args, "declination", None)
    location = location_instead_of(args, "--declination", declination)
    if location is not None:
        field = earth_field(*location.as_tuple(), args.date)
        return field.declination_deg, field.total_ut
    date_needs_location(args)
    return declination, None
