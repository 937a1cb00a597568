"""``magnet heading``: apply a calibration to a CSV of raw samples and print headings as CSV.

Columns: ``t_s`` (when the input has it), ``heading_deg`` (magnetic), ``true_heading_deg``, ``pitch_deg``,
``roll_deg``, ``field_x_ut``, ``field_y_ut``, ``field_z_ut``, ``dip_deg``, ``flags`` (magnet.heading.HeadingFlag),
``qw,qx,qy,qz`` (body -> NED with true north, i.e. the attitude whose heading is ``true_heading_deg``).

With ``gx,gy,gz`` (rad/s, body frame) and ``ax,ay,az`` the attitude comes from the gyroscope-aided filter
(``magnet.fusion``, flag FUSED): causal as the live compass runs it, or ``--offline`` (looks ahead: the best
estimate for a log). With ``vn,ve,vd`` (velocity over the ground, m/s, geographic NED; empty or NaN where unknown)
the filter removes the linear acceleration the velocity implies (``magnet.aiding``), as the live compass does. Its
sample period comes from ``--rate HZ`` or else the ``t_s`` column. Without a gyroscope the heading is tilt-
compensated with the accelerometer; without ``ax,ay,az`` it is the level heading and pitch and roll are 0 with the
NO_TILT flag. Without ``--calibration`` the raw field is used as it is (a factory-calibrated sensor, or a fit that
was refused).
"""

from __future__ import annotations

import argparse
import dataclasses
import sys

import numpy as np

from magnet import frames, fusion
from magnet import heading as hd
from magnet.autopilot import compare_headings
from magnet.frames import to_magnetic_ned
from magnet.geomag import earth_field, parse_location
from magnet.model import Calibration
from services.commands.fit import gyro_columns, sample_period_s
from services.common.csvio import SampleTable, write_csv
from services.common.input_options import InputOptions
from services.common.inputs import add_input_arguments, read_input_told, reference_yaw
from services.common.place import add_field_arguments
from services.common.records import load_calibration

COLUMNS = (
    "heading_deg",
    "true_heading_deg",
    "pitch_deg",
    "roll_deg",
    "field_x_ut",
    "field_y_ut",
    "field_z_ut",
    "dip_deg",
    "flags",
    "qw",
    "qx",
    "qy",
    "qz",
)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "file", metavar="FILE.csv", help="CSV with mx,my,mz (ax,ay,az for tilt; gx,gy,gz in rad/s and t_s for fusion)"
    )
    parser.add_argument(
        "--calibration",
        metavar="cal.json",
        help="a record as 'magnet fit' writes it ('offset' and 'matrix' are enough); default: none",
    )
    parser.add_argument("--declination", type=float, metavar="DEG", help="magnetic declination, degrees east")
    add_field_arguments(parser)
    add_input_arguments(parser)
    parser.add_argument(
        "--window",
        type=int,
        default=1,
        metavar="N",
        help="circular sliding-mean smoothing over N samples (default 1: none)",
    )
    parser.add_argument(
        "--rate", type=float, metavar="HZ", help="sample rate for the gyroscope fusion (default: from the t_s column)"
    )
    parser.add_argument(
        "--offline", action="store_true", help="with a gyroscope: the best estimate for a log (the filter looks ahead)"
    )
    parser.add_argument(
        "--compare",
        action="store_true",
        help="flight logs: print (stderr) the RMS difference to the autopilot's own logged yaw, after the constant "
        "offset",
    )


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


@dataclasses.dataclass(frozen=True)
class Attitude:
    """Per sample (N,): magnetic heading, pitch, roll, dip (degrees), body -> magnetic NED quat (N, 4), the
    down direction in body axes as a specific force (N, 3) (for the disturbance checks; None without tilt) and
    flags the method adds (FUSED, FIELD_DISTURBED from the filter)."""

    heading: np.ndarray
    pitch: np.ndarray
    roll: np.ndarray
    quat: np.ndarray
    up_force: np.ndarray | None
    flags: np.ndarray


def velocity_aiding(
    table: SampleTable, period_s: float, declination_deg: float
) -> tuple[np.ndarray | None, np.ndarray | None]:
    """(times (N,) s, velocities (N, 3) m/s in magnetic NED) from the vn,ve,vd columns (geographic NED, empty or NaN
    where unknown) and t_s (else the sample period), or (None, None) when the file has no velocity."""
    vel = table.vel_ned_ms()
    if vel is None:
        return None, None
    t_s = table.numeric("t_s") if "t_s" in table.columns else np.arange(len(vel)) * period_s
    return t_s, to_magnetic_ned(vel, declination_deg)


def _fused(
    table: SampleTable, gyr: np.ndarray, field: np.ndarray, args: argparse.Namespace, declination_deg: float
) -> Attitude:
    if table.acc is None:
        raise ValueError(f"{table.path}: gx,gy,gz need ax,ay,az too (the filter takes its tilt from gravity)")
    run = fusion.fuse_offline if args.offline else fusion.fuse_causal
    period_s = sample_period_s(table, args.rate)
    t_s, vel = velocity_aiding(table, period_s, declination_deg)
    fused = run(gyr, fusion.acc_in_ms2(table.acc), field, period_s, None, t_s, vel)
    down = frames.down_in_body(fused.quat_wxyz)
    flags = int(hd.HeadingFlag.FUSED) | np.where(fused.mag_disturbed, int(hd.HeadingFlag.FIELD_DISTURBED), 0)
    return Attitude(fused.heading_deg, fused.pitch_deg, fused.roll_deg, fused.quat_wxyz, -down, flags)


def _tilt(table: SampleTable, field: np.ndarray) -> Attitude:
    count = len(field)
    if table.acc is not None:
        magnetic = hd.tilt_compensated_heading_deg(field, table.acc)
        pitch, roll = hd.pitch_roll_deg(table.acc)
    else:
        magnetic = hd.level_heading_deg(field)
        pitch = roll = np.zeros(count)
    quat = frames.w_positive(frames.euler_to_quaternion(magnetic, pitch, roll))
    return Attitude(magnetic, pitch, roll, quat, table.acc, np.zeros(count, dtype=int))


def _accepted_calibration(path: str) -> Calibration:
    """The record of ``path`` (checked as plausible by ``load_calibration``); ValueError when it is marked not
    accepted: the gate refused it, and applying it could make every heading worse."""
    calibration = load_calibration(path)
    if not calibration.accepted:
        raise ValueError(
            f"{path}: this calibration was not accepted ({calibration.reason or 'no reason given'}): fit again "
            "with better coverage, or leave out --calibration to use the raw field"
        )
    return calibration


def _declination_words(args: argparse.Namespace, declination_deg: float) -> str:
    if args.location:
        return f"{declination_deg:.2f} deg (WMM2025 at --location)"
    if args.declination is not None:
        return f"{declination_deg:.2f} deg (--declination)"
    return "none (0 deg; give --declination or --location)"


def _compare(args: argparse.Namespace, table: SampleTable, true_deg: np.ndarray, declination_deg: float) -> None:
    """Print (stderr) how far magnet's headings are from the autopilot's own logged yaw: RMS after the constant
    offset, and the declination each used."""
    if "t_s" not in table.columns:
        raise ValueError(f"{table.path}: --compare needs the samples' times (t_s)")
    reference = reference_yaw(args.file)
    figures = compare_headings(table.numeric("t_s"), true_deg, reference.t_s, reference.yaw_deg)
    print(
        f"magnet heading: compare: {figures.rms_deg:.2f} deg RMS from the autopilot's {reference.source} yaw over "
        f"{figures.count} samples after removing a constant offset of {figures.offset_deg:+.2f} deg (max "
        f"{figures.max_deg:.2f} deg); declination: magnet {_declination_words(args, declination_deg)}, autopilot "
        f"{reference.declination}",
        file=sys.stderr,
    )


def run(args: argparse.Namespace) -> int:
    if args.window < 1:
        raise ValueError(f"--window must be at least 1, got {args.window}")
    calibration = _accepted_calibration(args.calibration) if args.calibration else None
    declination_deg, expected_ut, expected_dip_deg = _declination_deg(args)
    table = read_input_told(args.file, InputOptions.from_args(args), "heading")
    field = calibration.apply(table.mag) if calibration else np.asarray(table.mag, dtype=float)
    gyr = gyro_columns(table)
    if gyr is None and args.offline:
        raise ValueError(f"{table.path}: --offline needs gyroscope columns gx,gy,gz (rad/s)")
    attitude = _tilt(table, field) if gyr is None else _fused(table, gyr, field, args, declination_deg)
    magnetic = hd.smooth_heading_deg(attitude.heading, args.window)
    dip = hd.dip_angle_deg(field, attitude.up_force) if attitude.up_force is not None else np.full(len(field), np.nan)
    expected = expected_ut if expected_ut is not None else ((calibration and calibration.field_strength) or None)
    flags = np.asarray(hd.disturbance_flags(field, attitude.up_force, expected, expected_dip_deg), dtype=int)
    flags |= attitude.flags | (int(hd.HeadingFlag.CALIBRATED) if calibration else 0)
    if calibration and calibration.output_unit != "ut":
        print(
            f"magnet heading: note: the calibration's output unit is {calibration.output_unit!r}, not uT; "
            "field_*_ut columns are in that unit",
            file=sys.stderr,
        )
    quat = frames.rotate_heading(attitude.quat, declination_deg)
    if args.compare:
        _compare(args, table, hd.true_heading_deg(magnetic, declination_deg), declination_deg)
    header = list(COLUMNS)
    columns = [
        magnetic,
        hd.true_heading_deg(magnetic, declination_deg),
        attitude.pitch,
        attitude.roll,
        field[:, 0],
        field[:, 1],
        field[:, 2],
        dip,
        flags,
        *quat.T,
    ]
    formats = ["%.4f"] * 7 + ["%.3f", "%d"] + ["%.7f"] * 4  # 4 angles, 3 field components, dip, flags, quaternion
    if "t_s" in table.columns:
        header.insert(0, "t_s")
        columns.insert(0, table.numeric("t_s"))
        formats.insert(0, "%.6f")
    write_csv(sys.stdout, header, columns, fmt=formats)
    return 0
