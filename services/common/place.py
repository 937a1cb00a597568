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


def expected_field_ut(args: argparse.Namespace) -> float | None:
    """The field strength to scale to, in uT: --field-ut, or the WMM at --location, or None."""
    if args.field_ut is not None and args.location:
        raise ValueError("give either --field-ut or --location, not both")
    if args.field_ut is not None:
        if not (0 < args.field_ut < 1000):
            raise ValueError(f"--field-ut {args.field_ut} is not a plausible field strength in uT (Earth: 22-67)")
        return float(args.field_ut)
    if args.location:
        return earth_field(*Location.parse(args.location).as_tuple(), args.date).total_ut
    if args.date:
        raise ValueError("--date needs --location")
    return None


def place(args: argparse.Namespace) -> tuple[float | None, float | None]:
    """(declination deg, expected field uT) from --declination or --location/--date, each None when not given."""
    if getattr(args, "declination", None) is not None and args.location:
        raise ValueError("give either --declination or --location, not both")
    if args.location:
        field = earth_field(*Location.parse(args.location).as_tuple(), args.date)
        return field.declination_deg, field.total_ut
    if args.date:
        raise ValueError("--date needs --location")
    return getattr(args, "declination", None), None
