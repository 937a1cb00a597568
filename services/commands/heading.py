"""``magnet heading``: apply a calibration to a CSV of raw samples and print headings as CSV.

Columns: ``t_s`` (when the input has it), ``heading_deg`` (magnetic), ``true_heading_deg``, ``pitch_deg``,
``roll_deg``, ``field_x_ut``, ``field_y_ut``, ``field_z_ut``, ``dip_deg``, ``flags``
(magnet.attitude.heading.HeadingFlag), ``qw,qx,qy,qz`` (body -> NED with true north, i.e. the attitude whose heading is
``true_heading_deg``).

The headings come from the live compass's own step (``magnet.compass.CompassCore.step``): the file is one device's
raw batches (its runs of samples, cut where the time goes backwards or pauses for more than the filter's gap), so
``magnet heading`` prints what ``magnet compass`` publishes for the same samples. With ``gx,gy,gz`` (rad/s, body
frame) and ``ax,ay,az`` the attitude comes from the gyroscope-aided filter (``magnet.attitude.fusion``, flag FUSED),
causal as the live compass runs it; ``--offline`` is a different estimator (it looks ahead: the best estimate for a log,
not what the compass gives). With ``vn,ve,vd`` (velocity over the ground, m/s, geographic NED; empty or NaN where
unknown) the filter removes the linear acceleration the velocity implies (``magnet.attitude.aiding``). The samples'
times come from ``--rate HZ`` or else the ``t_s`` column. Without a gyroscope the heading is tilt-compensated with the
accelerometer; without ``ax,ay,az`` it is the level heading and pitch and roll are 0 with the NO_TILT flag. Without
``--calibration`` the raw field is used as it is (a factory-calibrated sensor, or a fit that was refused).
"""

from __future__ import annotations

import argparse
import datetime
import sys
import time

import numpy as np

from magnet import frames, wire
from magnet.attitude import fusion
from magnet.attitude import heading as hd
from magnet.compass import CompassCore, CoreSettings, HeadingColumns
from magnet.compass.calibrations import Correction
from magnet.compass.filters import MAX_GAP_S
from magnet.compass.tilt import Headings
from magnet.earth.expected import Earth, earth_at
from magnet.fleet.places import Places
from magnet.frames import to_magnetic_ned
from magnet.model import Calibration
from magnet.units import EARTH_MAX_UT, EARTH_MIN_UT
from services.commands.fit_motor import COLUMNS as MOTOR_COLUMNS
from services.common.inputs import add_input_arguments, read_input_told, reference_yaw
from services.common.inputs.csvio import SampleTable, gyro_columns, sample_period_s, write_csv
from services.common.inputs.input_options import InputOptions
from services.common.place import add_field_arguments, date_needs_location, location_instead_of
from services.common.records import load_calibration

#: the device the file's samples are, for the compass's core
FILE_DEVICE = "file"

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
        "--offline",
        action="store_true",
        help="with a gyroscope: the best estimate for a log, from its own estimator (the filter looks ahead, which "
        "the live compass cannot; without it the headings are the live compass's)",
    )
    parser.add_argument(
        "--force",
        action="store_true",
        help="apply --calibration even when the field it gives these samples is implausible (another device's "
        "record, or another unit)",
    )
    parser.add_argument(
        "--compare",
        action="store_true",
        help="flight logs: print (stderr) the RMS difference to the autopilot's own logged yaw, after the constant "
        "offset",
    )


def _earth(args: argparse.Namespace, calibration: Calibration | None) -> Earth:
    """What to expect: the WMM at --location on --date (default today), or --declination; the field strength is the
    calibration's own where the model gives none."""
    location = location_instead_of(args, "--declination", args.declination)
    if location is not None:
        return earth_at(location, args.date or datetime.date.today())
    date_needs_location(args)
    if args.declination is not None and not -180 <= args.declination <= 180:
        raise ValueError(f"--declination {args.declination} is outside -180..180 degrees")
    strength = (calibration.field_strength or None) if calibration is not None else None
    return Earth(float(args.declination or 0.0), strength, None)


def file_times_ns(table: SampleTable, rate_hz: float | None, gyro: bool) -> np.ndarray:
    """The samples' times (N,) int64 ns: the ``t_s`` column's, or every 1 / --rate from the first (0 without
    ``t_s``); kept as the recording's intervals from the first sample, as ``magnet edge --replay`` stamps them."""
    count = len(table.mag)
    t_s = table.numeric("t_s") if "t_s" in table.columns else None
    first_ns = int(np.round(t_s[0] * 1e9)) if t_s is not None and count else 0
    if gyro or rate_hz is not None:
        period_s = sample_period_s(table, rate_hz)
        if rate_hz is not None or t_s is None:
            return first_ns + np.round(np.arange(count) * period_s * 1e9).astype(np.int64)
    if t_s is None:
        return np.arange(count, dtype=np.int64) * 10_000_000
    return first_ns + np.round((t_s - t_s[0]) * 1e9).astype(np.int64)


def sample_runs(t_ns: np.ndarray) -> np.ndarray:
    """Samples per run (R,): the file cut where the time does not go forward or pauses longer than the filter's
    gap, as a device's batches would be (a batch's times go forward; a gap restarts its filter)."""
    cuts = np.flatnonzero((np.diff(t_ns) <= 0) | (np.diff(t_ns) > MAX_GAP_S * 1e9)) + 1
    return np.diff(np.concatenate([[0], cuts, [len(t_ns)]])).astype(np.int64)


def file_columns(table: SampleTable, gyr: np.ndarray | None, rate_hz: float | None) -> wire.RawColumns:
    """The file as one device's raw batches (its sample runs), float64, acc in m/s^2 (``fusion.acc_in_ms2``)."""
    if gyr is not None and table.acc is None:
        raise ValueError(f"{table.path}: gx,gy,gz need ax,ay,az too (the filter takes its tilt from gravity)")
    count = len(table.mag)
    t_ns = file_times_ns(table, rate_hz, gyr is not None)
    counts = sample_runs(t_ns) if count else np.zeros(0, dtype=np.int64)
    nan_rows = np.broadcast_to(np.nan, (count, 3))  # read only, made only where a column is absent
    vel = table.vel_ned_ms()
    motors = {name: table.numeric(name, missing_ok=True) for name in MOTOR_COLUMNS.values() if name in table.columns}
    return wire.RawColumns(
        [FILE_DEVICE] * len(counts),
        list(range(len(counts))),
        counts,
        t_ns,
        np.asarray(table.mag, dtype=np.float64),
        nan_rows if table.acc is None else fusion.acc_in_ms2(table.acc),
        nan_rows if gyr is None else np.asarray(gyr, dtype=np.float64),
        ["file"] * len(counts),
        None,
        nan_rows if vel is None else vel,  # read only: no 1.4 MB of NaN per 60,000 rows
        motors.get("current_a"),
        motors.get("throttle"),
    )


def file_fields(
    table: SampleTable, gyr: np.ndarray, calibration: Calibration | None, rate_hz: float | None
) -> tuple[np.ndarray, np.ndarray]:
    """(the corrected field (N, 3) uT, the field (N, 3) the attitude filter gets) of the file's samples by the
    record, through the compass's one correction (``magnet.compass.calibrations.Correction``: offset, matrix, the
    motors' field where the file has ``current_a`` or ``throttle``, and the magnetometer's lag); the raw field twice
    without a record."""
    raw = file_columns(table, gyr, rate_hz)
    record = wire.DeviceCalibration(FILE_DEVICE, 0, calibration) if calibration is not None else None
    return Correction.of_batches([record] * len(raw.counts), raw).apply(raw.mag_ut, raw.gyr_rads)


def causal_headings(
    raw: wire.RawColumns, calibration: Calibration | None, earth: Earth, window: int, now_ns: int
) -> HeadingColumns:
    """The live compass's step on the file's columns, with the calibration in force and ``earth`` expected (without
    the sigmas, which the command does not print)."""
    core = CompassCore(CoreSettings(window, drift=None, sigmas=False), Places(default_earth=earth))
    if calibration is not None:
        core.calibrations.put(wire.DeviceCalibration(FILE_DEVICE, now_ns, calibration))
    return core.step(raw, now_ns)


def offline_headings(
    table: SampleTable, gyr: np.ndarray, calibration: Calibration | None, args: argparse.Namespace, earth: Earth
) -> HeadingColumns:
    """``--offline``: its own estimator, not the compass's (vqf's offline filter looks ahead over the whole log),
    on the field the record corrects as the compass does (``file_fields``)."""
    if table.acc is None:
        raise ValueError(f"{table.path}: gx,gy,gz need ax,ay,az too (the filter takes its tilt from gravity)")
    field, filter_field = file_fields(table, gyr, calibration, args.rate)
    blind = hd.no_earth_field(field, earth.total_ut) if calibration is None else np.zeros(len(field), dtype=bool)
    # as the compass: no record, no Earth field; none at all goes without the magnetometer (vqf's offline filter
    # given only zero fields turns its heading: 35 deg RMS on a simulated walk, against 6.5 without one)
    mag: np.ndarray | None = None if blind.all() else np.where(blind[:, None], 0.0, filter_field)
    period_s = sample_period_s(table, args.rate)
    vel = table.vel_ned_ms()
    t_s = None
    if vel is not None:
        t_s = table.numeric("t_s") if "t_s" in table.columns else np.arange(len(vel)) * period_s
        vel = to_magnetic_ned(vel, earth.declination_deg)
    fused = fusion.fuse_offline(gyr, fusion.acc_in_ms2(table.acc), mag, period_s, None, t_s, vel)
    down = frames.down_in_body(fused.quat_wxyz)
    dip = hd.dip_angle_deg(field, -down)
    flags = hd.disturbance_flags(field, -down, earth.total_ut, earth.inclination_deg, dip_deg=dip)
    disturbed = fused.mag_disturbed | blind
    flags |= int(hd.HeadingFlag.FUSED) | np.where(disturbed, int(hd.HeadingFlag.FIELD_DISTURBED), 0)
    flags |= int(hd.HeadingFlag.CALIBRATED) if calibration is not None else 0
    magnetic = hd.smooth_heading_deg(fused.heading_deg, args.window)
    headings = Headings(field, magnetic, fused.pitch_deg, fused.roll_deg, flags)
    quat = frames.rotate_heading(fused.quat_wxyz, earth.declination_deg)
    true = hd.true_heading_deg(magnetic, earth.declination_deg)
    return HeadingColumns(headings, true, dip, [], [earth.declination_deg], quat)


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


#: the corrected field's median strength may be this far from the expected before the record is called implausible
#: for the samples (a record fitted on the same sensor lands within a few per cent; another device's hard iron or a
#: unit off by 100 lands far outside)
PLAUSIBLE_FIELD_PCT = 25.0


def implausible_field(calibration: Calibration, mag: np.ndarray, earth: Earth) -> str | None:
    """Why ``calibration`` applied to ``mag`` (N, 3) gives no plausible field, or None: the median corrected |B| (uT)
    against the expected strength (the WMM's, else the record's own), or the Earth's range when neither is known."""
    if calibration.output_unit != "ut" or not len(mag):
        return None
    strength = float(np.nanmedian(np.linalg.norm(calibration.apply(mag), axis=1)))
    expected = earth.total_ut or calibration.field_strength or None
    if expected is not None:
        if abs(strength / expected - 1.0) * 100.0 <= PLAUSIBLE_FIELD_PCT:
            return None
        against = f"the expected {expected:.1f} uT"
    elif EARTH_MIN_UT <= strength <= EARTH_MAX_UT:
        return None
    else:
        against = f"any Earth field ({EARTH_MIN_UT:g}-{EARTH_MAX_UT:g} uT)"
    return (
        f"the calibration gives these samples a field of {strength:.3g} uT, not {against}: it is probably another "
        "device's record or the samples are in another unit (--unit); --force applies it anyway"
    )


def _declination_words(args: argparse.Namespace, declination_deg: float) -> str:
    if args.location:
        return f"{declination_deg:.2f} deg (WMM2025 at --location)"
    if args.declination is not None:
        return f"{declination_deg:.2f} deg (--declination)"
    return "none (0 deg; give --declination or --location)"


def _compare(args: argparse.Namespace, table: SampleTable, true_deg: np.ndarray, declination_deg: float) -> None:
    """Print (stderr) how far magnet's headings are from the autopilot's own logged yaw: RMS after the constant
    offset, and the declination each used."""
    from magnet.autopilot.conventions import compare_headings  # flight logs only

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


def _attitude_wxyz(out: HeadingColumns) -> np.ndarray:
    """(N, 4) body -> NED (true north): the filter's where it fused, else the one of the heading, pitch and roll."""
    h = out.headings
    fused = out.quat_wxyz
    finite = None if fused is None else hd.rows_finite(fused)
    if fused is not None and finite is not None and finite.all():  # fused on every row: no angles' quaternion used
        return fused
    quat = frames.w_positive(frames.euler_to_quaternion(out.true_heading_deg, h.pitch_deg, h.roll_deg))
    return quat if fused is None or finite is None else np.where(finite[:, None], fused, quat)


def run(args: argparse.Namespace) -> int:
    CoreSettings(window=args.window)  # --window checked (the compass's own check) before the file is read
    calibration = _accepted_calibration(args.calibration) if args.calibration else None
    earth = _earth(args, calibration)
    table = read_input_told(args.file, InputOptions.from_args(args), "heading")
    implausible = implausible_field(calibration, table.mag, earth) if calibration else None
    if implausible and not args.force:
        raise ValueError(f"{args.calibration}: {implausible}")
    if implausible:
        print(f"magnet heading: warning: {implausible}", file=sys.stderr)
    gyr = gyro_columns(table)
    if args.offline:
        if gyr is None:
            raise ValueError(f"{table.path}: --offline needs gyroscope columns gx,gy,gz (rad/s)")
        out = offline_headings(table, gyr, calibration, args, earth)
    else:
        out = causal_headings(file_columns(table, gyr, args.rate), calibration, earth, args.window, time.time_ns())
    if calibration and calibration.output_unit != "ut":
        print(
            f"magnet heading: note: the calibration's output unit is {calibration.output_unit!r}, not uT; "
            "field_*_ut columns are in that unit",
            file=sys.stderr,
        )
    if args.compare:
        _compare(args, table, out.true_heading_deg, earth.declination_deg)
    write_headings(table, out)
    return 0


def write_headings(table: SampleTable, out: HeadingColumns) -> None:
    """The CSV of ``out`` on stdout (with the file's ``t_s`` when it has one)."""
    h = out.headings
    header = list(COLUMNS)
    columns = [
        h.heading_deg,
        out.true_heading_deg,
        h.pitch_deg,
        h.roll_deg,
        h.field_ut[:, 0],
        h.field_ut[:, 1],
        h.field_ut[:, 2],
        out.dip_deg,
        h.flags,
        *_attitude_wxyz(out).T,
    ]
    formats = ["%.4f"] * 7 + ["%.3f", "%d"] + ["%.7f"] * 4  # 4 angles, 3 field components, dip, flags, quaternion
    if "t_s" in table.columns:
        header.insert(0, "t_s")
        columns.insert(0, table.numeric("t_s"))
        formats.insert(0, "%.6f")
    write_csv(sys.stdout, header, columns, fmt=formats)
