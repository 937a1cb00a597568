"""``magnet fit``: fit a calibration to a CSV of raw samples and write the record as JSON.

Exit status 0 when the quality gate accepts the fit; 1 when it is rejected (the reason on stderr, an existing
``--out`` file left untouched); 2 for bad input (one line on stderr).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

from magnet.calibration import FitInput, Method, TurntableSetup, sample_runs
from magnet.calibration.choose import AUTO, CHOICES, fit_choice
from magnet.earth.location import Location
from magnet.model import Calibration
from magnet.units import FieldUnit
from services.commands.fit_motor import add_motor_arguments, fit_with_motors
from services.common.inputs import add_input_arguments, read_input_told
from services.common.inputs.csvio import SampleTable, gyro_columns, sample_period_s
from services.common.inputs.input_options import InputOptions
from services.common.place import add_field_arguments, expected_field_ut
from services.common.records import load_calibration, write_atomically

EXIT_REJECTED = 1


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "file",
        metavar="FILE.csv",
        help="CSV with a header row: mx,my,mz required; ax,ay,az, gx,gy,gz (rad/s) and t_s optional",
    )
    parser.add_argument(
        "--method",
        default=AUTO,
        choices=CHOICES,
        help="auto (the default): with gx,gy,gz and the sample times, fit gyro-ellipsoid and ellipsoid and keep the "
        "accepted one (both accepted: the one whose field is more constant on held-out data), else ellipsoid; "
        "both refused: the model the motion identifies (offset, offset+scale, planar or ellipsoid; --location gives "
        "the WMM's dip as a prior). gyro-ellipsoid needs gx,gy,gz and the sample times (t_s or --rate); offset, "
        "offset+scale and planar fit that rung of the field ladder",
    )
    parser.add_argument(
        "--unit", default="ut", choices=[u.value for u in FieldUnit], help="unit of the mx,my,mz columns (default ut)"
    )
    parser.add_argument("--field-ut", type=float, metavar="F", help="expected field strength in uT")
    add_input_arguments(parser)
    add_field_arguments(parser)
    parser.add_argument(
        "--horizontal",
        type=float,
        metavar="H",
        help="turntable: known horizontal field component (its unit is the output unit)",
    )
    parser.add_argument(
        "--vertical",
        type=float,
        metavar="V",
        help="turntable: known vertical component along the upward axis (negative in the north)",
    )
    parser.add_argument(
        "--field-unit",
        default="ut",
        choices=[u.value for u in FieldUnit if u is not FieldUnit.COUNTS],
        help="turntable: unit of --horizontal/--vertical and of the corrected field (default ut; nt for gammas)",
    )
    parser.add_argument(
        "--turntable-variant",
        default="closed",
        choices=("closed", "lsq"),
        help="turntable: closed form from the 0/90/180/270 readings (seed 000) or least squares over every angle",
    )
    parser.add_argument(
        "--robust-extremes",
        action="store_true",
        help="minmax: pull each new extreme in slowly (0.2 new, 0.8 old) to resist spikes",
    )
    parser.add_argument(
        "--rate",
        type=float,
        metavar="HZ",
        help="sample rate for the gyroscope columns gx,gy,gz (default: from the t_s column)",
    )
    parser.add_argument(
        "--in-force",
        metavar="cal.json",
        help="the calibration in force: the fit must make the field more constant than it does "
        "(default: than no calibration)",
    )
    parser.add_argument(
        "--keep-disturbed",
        action="store_true",
        help="fit every sample, also those in a disturbed field (by default left out: docs/field-calibration.md)",
    )
    add_motor_arguments(parser)
    parser.add_argument("--out", metavar="cal.json", help="write the record here (default: stdout)")
    parser.add_argument(
        "--report",
        metavar="FILE",
        help="also draw a report of this fit (.html, .png or .pdf; see 'magnet report'), accepted or not",
    )


def _turntable_setup(table: SampleTable, args: argparse.Namespace) -> TurntableSetup:
    if args.horizontal is None or args.vertical is None:
        raise ValueError("the turntable method needs --horizontal and --vertical (the known field components)")
    return TurntableSetup(
        np.asarray(table.text("mounting")),
        table.numeric("heading_deg"),
        args.horizontal,
        args.vertical,
        args.turntable_variant,
        field_unit=args.field_unit,
    )


def fit_input(table: SampleTable, args: argparse.Namespace) -> FitInput:
    """The fit's input from the samples and the options (ValueError for options that do not fit the file)."""
    if args.method == Method.TURNTABLE.value:
        return FitInput(table.mag, unit=args.unit, turntable=_turntable_setup(table, args))
    if args.horizontal is not None or args.vertical is not None:
        raise ValueError("--horizontal/--vertical are for --method turntable only")
    auto = args.method == AUTO
    gyr = gyro_columns(table) if table.acc is not None or args.method in (AUTO, Method.GYRO_ELLIPSOID.value) else None
    if gyr is None and args.method == Method.GYRO_ELLIPSOID.value:
        raise ValueError(f"{table.path}: --method gyro-ellipsoid needs the gyroscope columns gx,gy,gz (rad/s)")
    if auto and gyr is not None and args.rate is None and "t_s" not in table.columns:
        gyr = None  # auto without the sample times: the ellipsoid, which needs none
    period = sample_period_s(table, args.rate) if gyr is not None else None
    if gyr is not None and period is not None and args.rate is None:
        gyr = _over_missing(gyr, table.numeric("t_s"), period)
    in_force = load_calibration(args.in_force) if args.in_force else None
    field_ut = expected_field_ut(args)
    return FitInput(
        table.mag,
        unit=args.unit,
        t_s=table.numeric("t_s") if period is not None and args.rate is None else None,  # read for the period
        acc=table.acc,
        gyr_rads=gyr,
        period_s=period,
        place=Location.parse(args.location) if args.location else None,
        date=args.date,
        field_ut=field_ut,
        robust_extremes=args.robust_extremes,
        reference=in_force,
        vel_ned_ms=table.vel_ned_ms() if gyr is not None else None,  # vn,ve,vd: the field ladder's aided attitude
        drop_disturbed=not getattr(args, "keep_disturbed", False),
    )


def _over_missing(gyr_rads: np.ndarray, t_s: np.ndarray, period_s: float) -> np.ndarray:
    """The rates (N, 3) rad/s with the sample after k missing ones (t_s (N,) s, a step of k + 1 periods of period_s)
    k + 1 times, up to 3 missing (``sample_runs.whole_periods``, the compass's rule): a file that dropped samples
    keeps their rotation; one without gaps is read as it is."""
    periods = sample_runs.whole_periods(np.round(np.asarray(t_s, dtype=float) * 1e9).astype(np.int64), period_s * 1e9)
    return gyr_rads if periods is None else gyr_rads * periods[:, None]


def fit_table(table: SampleTable, args: argparse.Namespace) -> Calibration:
    """Run the chosen method (or auto) on the samples, with the motors' field when asked."""
    data = fit_input(table, args)
    if getattr(args, "motor", None) and data.turntable is None:
        return fit_with_motors(
            table, args.motor, lambda mag: fit_choice(data.replace(mag=mag), args.method), data.field_ut
        )
    return fit_choice(data, args.method)


def run(args: argparse.Namespace) -> int:
    from services.common.progress import steps

    options = InputOptions.from_args(args)
    with steps(["fit: reading samples", "fit: fitting and gating"]) as step:  # a bar only on a terminal
        step("fit: reading samples")
        table = read_input_told(args.file, options, "fit")
        step("fit: fitting and gating")
        calibration = fit_table(table, args)
    if args.report:
        from services.common.place import place
        from services.report.write import write_report

        write_report(args.report, args.file, calibration, args.unit, *place(args), options)
    text = json.dumps(calibration.to_dict(), indent=2) + "\n"
    if not calibration.accepted:
        print(f"magnet fit: rejected: {calibration.reason}", file=sys.stderr)
        if not args.out:
            sys.stdout.write(text)
        return EXIT_REJECTED
    if args.out:
        write_atomically(Path(args.out), text)
        print(f"magnet fit: {summary(calibration)}; written to {args.out}")
    else:
        sys.stdout.write(text)
    return 0


def summary(calibration: Calibration) -> str:
    """One line on an accepted record: method, offset in its unit and the gate's words."""
    offset = ", ".join(f"{v:.2f}" for v in calibration.offset)
    return f"{calibration.method}, offset ({offset}) {calibration.unit}, {calibration.reason}"
