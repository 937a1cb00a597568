"""``magnet heading``: apply a calibration to a CSV of raw samples and print headings as CSV.

Columns: ``t_s`` (when the input has it), ``heading_deg`` (magnetic), ``true_heading_deg``, ``pitch_deg``,
``roll_deg``, ``field_x_ut``, ``field_y_ut``, ``field_z_ut``, ``dip_deg``, ``flags`` (magnet.heading.HeadingFlag).
Without ``ax,ay,az`` the heading is the level heading and pitch and roll are 0 with the NO_TILT flag.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

from magnet import heading as hd
from magnet.geomag import earth_field, parse_location
from magnet.model import Calibration
from services.common.csvio import read_samples, write_csv
from services.commands.fit import add_field_arguments

COLUMNS = ("heading_deg", "true_heading_deg", "pitch_deg", "roll_deg", "field_x_ut", "field_y_ut", "field_z_ut",
           "dip_deg", "flags")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("file", metavar="FILE.csv", help="CSV with mx,my,mz (and ax,ay,az for tilt compensation)")
    parser.add_argument("--calibration", required=True, metavar="cal.json",
                        help="a record as 'magnet fit' writes it ('offset' and 'matrix' are enough)")
    parser.add_argument("--declination", type=float, metavar="DEG", help="magnetic declination, degrees east")
    add_field_arguments(parser)
    parser.add_argument("--window", type=int, default=1, metavar="N",
                        help="circular sliding-mean smoothing over N samples (default 1: none)")


def load_calibration(path: str) -> Calibration:
    try:
        data = json.loads(Path(path).read_text())
    except json.JSONDecodeError as exc:
        raise ValueError(f"{path}: not JSON ({exc.msg} at line {exc.lineno})") from None
    try:
        return Calibration.from_dict(data)
    except ValueError as exc:
        raise ValueError(f"{path}: {exc}") from None


def _declination_deg(args: argparse.Namespace) -> tuple[float, float | None, float | None]:
    """(declination, expected field uT or None, expected dip deg or None) from the options."""
    if args.declination is not None and args.location:
        raise ValueError("give either --declination or --location, not both")
    if args.location:
        lat, lon, alt_m = parse_location(args.location)
        field = earth_field(lat, lon, alt_m, args.date)
        return field.declination_deg, field.total_ut, field.inclination_deg
    if args.date:
        raise ValueError("--date needs --location")
    if args.declination is not None and not -180 <= args.declination <= 180:
        raise ValueError(f"--declination {args.declination} is outside -180..180 degrees")
    return float(args.declination or 0.0), None, None


def run(args: argparse.Namespace) -> int:
    if args.window < 1:
        raise ValueError(f"--window must be at least 1, got {args.window}")
    calibration = load_calibration(args.calibration)
    declination_deg, expected_ut, expected_dip_deg = _declination_deg(args)
    table = read_samples(args.file)
    field = calibration.apply(table.mag)
    count = len(field)
    if table.acc is not None:
        magnetic = hd.tilt_compensated_heading_deg(field, table.acc)
        pitch, roll = hd.pitch_roll_deg(table.acc)
        dip = hd.dip_angle_deg(field, table.acc)
    else:
        magnetic = hd.level_heading_deg(field)
        pitch = roll = np.zeros(count)
        dip = np.full(count, np.nan)
    magnetic = hd.smooth_heading_deg(magnetic, args.window)
    expected = expected_ut if expected_ut is not None else (calibration.field_strength or None)
    flags = hd.disturbance_flags(field, table.acc, expected, expected_dip_deg)
    flags = np.asarray(flags, dtype=int) | int(hd.HeadingFlag.CALIBRATED)
    if calibration.output_unit != "ut":
        print(f"magnet heading: note: the calibration's output unit is {calibration.output_unit!r}, not uT; "
              "field_*_ut columns are in that unit", file=sys.stderr)
    header = list(COLUMNS)
    columns = [magnetic, hd.true_heading_deg(magnetic, declination_deg), pitch, roll,
               field[:, 0], field[:, 1], field[:, 2], dip, flags]
    if "t_s" in table.columns:
        header.insert(0, "t_s")
        columns.insert(0, table.numeric("t_s"))
    formats = ["%.4f"] * 7 + ["%.3f", "%d"]  # 4 angles, 3 field components, dip, flags
    if "t_s" in table.columns:
        formats.insert(0, "%.6f")
    write_csv(sys.stdout, header, columns, fmt=formats)
    return 0
