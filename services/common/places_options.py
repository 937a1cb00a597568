"""The places file ``--fleet FILE.json5`` (device -> location, notes; see ``magnet.fleet.places``) and the drift
thresholds, as options of the compass and the calibrator, read and checked before a service starts."""

from __future__ import annotations

import argparse
from pathlib import Path

from magnet.drift import DriftSettings
from magnet.fleet.places import MAX_PLACES_FILE_BYTES, PlaceEntry, parse_places


def add_fleet_argument(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--fleet",
        type=Path,
        metavar="FILE.json5",
        help='places file: device id -> {location: "LAT,LON[,ALT_M]", notes}; a device\'s own '
        "reported location wins, --location is the default for the others",
    )


def read_fleet(path: Path | None) -> dict[str, PlaceEntry]:
    """The places file's entries ({} without one); ValueError with the file and what is wrong."""
    if path is None:
        return {}
    try:
        if path.stat().st_size > MAX_PLACES_FILE_BYTES:
            raise ValueError(f"--fleet {path}: larger than {MAX_PLACES_FILE_BYTES} bytes")
        text = path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        raise ValueError(f"--fleet {path}: cannot read it: {exc}") from None
    return parse_places(text, f"--fleet {path}")


#: the drift options: (flag, DriftSettings field it sets, type, metavar, help with {default})
DRIFT_OPTIONS: tuple[tuple[str, str, type, str | None, str], ...] = (
    ("--drift-window", "window_s", float, "S", "seconds per judged window (default {default:g})"),
    (
        "--drift-windows",
        "raise_windows",
        int,
        "N",
        "departed windows in a row before an alert, and recovered ones before it clears (default {default})",
    ),
    (
        "--strength-tol-pct",
        "strength_tol_pct",
        float,
        None,
        "|B| departure from the calibration's own, %% (default {default:g})",
    ),
    (
        "--dip-tol",
        "dip_tol_deg",
        float,
        "DEG",
        "dip departure from the calibration's own, degrees (default {default:g})",
    ),
    ("--max-age-days", "max_age_days", float, None, "calibration age that raises an alert (default {default:g})"),
)


def add_drift_arguments(parser: argparse.ArgumentParser) -> None:
    defaults = DriftSettings()
    group = parser.add_argument_group("drift alerts (see README: Fleet operations)")
    group.add_argument("--no-drift", action="store_true", help="publish no drift alerts")
    for flag, field, kind, metavar, text in DRIFT_OPTIONS:
        default = getattr(defaults, field)
        group.add_argument(flag, type=kind, default=default, metavar=metavar, help=text.format(default=default))


def drift_from_args(args: argparse.Namespace) -> DriftSettings | None:
    """The checked drift settings, None with --no-drift; ValueError naming the option otherwise."""
    if args.no_drift:
        return None
    try:
        return DriftSettings(
            window_s=args.drift_window,
            raise_windows=args.drift_windows,
            clear_windows=args.drift_windows,
            strength_tol_pct=args.strength_tol_pct,
            dip_tol_deg=args.dip_tol,
            max_age_days=args.max_age_days,
        )
    except ValueError as exc:
        raise ValueError(f"drift options: {exc}") from None
