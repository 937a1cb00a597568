"""``magnet export (--calibration FILE | --device ID) --format ardupilot|px4 [--instance N] [--out FILE]``.

Writes the parameters that make the autopilot apply a calibration (the maths in ``magnet.autopilot.params``):

- ``ardupilot``: ``NAME,VALUE`` lines, as Mission Planner saves a .param file and MAVProxy's ``param load`` reads it
  (``#`` lines are comments);
- ``px4``: QGroundControl's .params layout, one tab-separated ``vehicle-id component-id name value type`` line per
  parameter (type 9 a 32-bit float, 6 a 32-bit integer), after ``#`` comment lines.

``--apply URL`` also sets them on a vehicle over MAVLink (``services.commands.export_apply``) as a transaction: each
is read back, a vehicle whose autopilot is armed is refused (checked between writes too), and on any failure the old
values are put back and the error names those restored and any that could not be; what changed is printed
(old -> new). A record that names its sensor (``hardware_id``) writes the id parameter first (``COMPASS_DEV_IDn``,
``CAL_MAGn_ID``); ``--apply`` reads it from the vehicle instead of writing it and refuses when it names another sensor.
After the apply (``services.commands.export_after``): ``--reboot`` reboots the autopilot (refused while armed), else
a line says it needs one; then its compass is watched for ``--check-s`` seconds (default 60, 0: not) and the command
says whether the vehicle now agrees with the record (ArduPilot).

``--device ID`` asks the calibrator for the device's calibration in force (as ``magnet get calibration ID`` does).
Exit status 0 with the file written; 1 when no calibrator answered; 2 for bad input or a calibration the autopilot
cannot represent (the reason on stderr; an existing ``--out`` file is left untouched); 3 when the parameters were
applied but the check says the vehicle does not agree.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

from magnet.autopilot.mavlink_stream import compass_instance
from magnet.autopilot.params import Autopilot, Export, export_parameters
from magnet.frames import ROTATIONS
from magnet.model import Calibration
from services.common.jsonio import read_json
from services.common.mavlink_options import add_mavlink_url_arguments
from services.common.records import load_calibration, write_atomically
from services.common.zenoh_session import add_zenoh_arguments

#: MAVLink's MAV_PARAM_TYPE of a 32-bit float and of a 32-bit integer, as QGroundControl writes them
PX4_REAL32 = 9
PX4_INT32 = 6


def add_arguments(parser: argparse.ArgumentParser) -> None:
    source = parser.add_mutually_exclusive_group(required=True)
    source.add_argument("--calibration", metavar="cal.json", help="a record as 'magnet fit' writes it")
    source.add_argument("--device", metavar="ID", help="ask the calibrator for this device's calibration in force")
    parser.add_argument("--format", required=True, choices=[a.value for a in Autopilot], help="the autopilot")
    parser.add_argument(
        "--instance",
        type=int,
        metavar="N",
        help="compass instance / calibration slot (default: the device's own, mav1-mag2: 2; else 0)",
    )
    parser.add_argument(
        "--rotation-in-force",
        type=int,
        default=0,
        metavar="R",
        help="the orientation parameter (COMPASS_ORIENTn / CAL_MAGn_ROT or SENS_BOARD_ROT) in force when the "
        "samples were recorded (default 0: none)",
    )
    parser.add_argument("--vehicle-id", type=int, default=1, help="px4: the vehicle (system) id column (default 1)")
    parser.add_argument("--out", metavar="FILE", help="write here (default: stdout)")
    parser.add_argument("--timeout", type=float, default=3.0, help="--device: seconds to wait for the calibrator")
    add_mavlink_url_arguments(
        parser,
        "--apply",
        "also set the parameters on a vehicle over MAVLink (pymavlink URL: udpin:HOST:PORT, udpout:..., tcp:..., "
        "or a serial device), reading each back; refused while the vehicle is armed",
        "--apply over a serial device: its baud rate",
    )
    parser.add_argument(
        "--reboot", action="store_true", help="--apply: then reboot the autopilot (refused while it is armed)"
    )
    parser.add_argument(
        "--check-s",
        type=float,
        default=60.0,
        metavar="S",
        help="--apply: then watch the vehicle's compass this long and say whether it agrees with the record "
        "(default 60; 0: no check)",
    )
    add_zenoh_arguments(parser)


def _from_device(args: argparse.Namespace) -> Calibration | None:
    """The device's calibration in force, from the calibrator; None when nobody answered."""
    from magnet import wire
    from services.commands.remote import ask
    from services.common.endpoint import use_local_pipeline

    use_local_pipeline(args)  # no Zenoh option given: the running magnet up, as magnet get finds it
    wire.validate_device_id(args.device)
    replies = ask(args, f"{args.prefix}/{args.device}/{wire.Kind.CALIBRATION.value}")
    if not replies:
        return None
    try:
        return wire.calibration_from_record(replies[0]).calibration
    except wire.WireError as exc:
        raise ValueError(f"the calibrator's answer for {args.device} is unusable: {exc}") from None


def _device_of(path: str) -> str | None:
    """The device id a record file names (``magnet get calibration --json`` writes it), if it names one."""
    data = read_json(path)
    device = data.get("device") if isinstance(data, dict) else None
    return device if isinstance(device, str) else None


def _value(value: float, integer: bool) -> str:
    return str(round(value)) if integer else f"{value:.9g}"


def render(export: Export, source: str, vehicle_id: int = 1) -> str:
    """The parameter file's text for ``export`` (see the module docstring); ``source`` names the record."""
    comments = [f"# magnet export: {source}", *(f"# note: {note}" for note in export.notes)]
    if export.autopilot is Autopilot.ARDUPILOT:
        lines = [f"{p.name},{_value(p.value, p.integer)}" for p in export.parameters]
        return "\n".join([*comments, *lines]) + "\n"
    header = [f"# Onboard parameters for Vehicle {vehicle_id}", "#", "# Vehicle-Id Component-Id Name Value Type"]
    lines = [
        f"{vehicle_id}\t1\t{p.name}\t{_value(p.value, p.integer)}\t{PX4_INT32 if p.integer else PX4_REAL32}"
        for p in export.parameters
    ]
    return "\n".join([*header, *comments, *lines]) + "\n"


def run(args: argparse.Namespace) -> int:
    if args.rotation_in_force not in ROTATIONS:
        raise ValueError(f"--rotation-in-force {args.rotation_in_force} is not a named orientation magnet knows")
    device = args.device
    if args.calibration:
        calibration, source = load_calibration(args.calibration), args.calibration
        device = _device_of(args.calibration)
    else:
        found = _from_device(args)
        if found is None:
            print(f"magnet export: no calibration for {args.device} (is a calibrator reachable?)", file=sys.stderr)
            return 1
        calibration, source = found, f"device {args.device}"
    if not calibration.accepted:
        raise ValueError(f"{source}: this calibration was not accepted ({calibration.reason}): export a good one")
    instance = args.instance
    if instance is None:
        named = compass_instance(device)
        instance = named or 0
        if named is not None:
            print(f"magnet export: note: instance {instance}, from the device id {device}", file=sys.stderr)
    export = export_parameters(calibration, args.format, instance, args.rotation_in_force)
    text = render(export, f"{source} (method {calibration.method}, id {calibration.content_id})", args.vehicle_id)
    for note in export.notes:
        print(f"magnet export: note: {note}", file=sys.stderr)
    if args.out:
        write_atomically(Path(args.out), text)
    elif not args.apply:
        sys.stdout.write(text)
    if args.reboot and not args.apply:
        raise ValueError("--reboot goes with --apply URL")
    if args.apply:
        return _apply(args, export, calibration, instance)
    return 0


def _apply(args: argparse.Namespace, export: Export, calibration: Calibration, instance: int) -> int:
    """Set the exported parameters on the vehicle at ``--apply`` and print what changed (stdout); then reboot and
    check it (``export_after``): 0, or 3 when it does not agree."""
    from services.commands.export_after import after_apply
    from services.commands.export_apply import apply_params

    if not np.isfinite(args.check_s) or args.check_s < 0:
        raise ValueError(f"--check-s must be a number of seconds >= 0, got {args.check_s}")

    values = {p.name: p.value for p in export.parameters if not p.check_only}
    sensors = {p.name: round(p.value) for p in export.parameters if p.check_only}
    report = apply_params(args.apply, values, baud=args.baud, sensors=sensors)
    print(f"magnet export: vehicle {report.sysid} (component {report.compid}):")
    for line in report.lines():
        print(f"  {line}")
    before = {c.name: c.old for c in report.changes if c.old is not None}
    after = {c.name: c.read_back for c in report.changes}
    if export.autopilot is not Autopilot.ARDUPILOT:
        args.check_s = 0.0  # PX4's SCALED_IMU carries the uncorrected reading: nothing of its correction to check
    if args.check_s:
        print(f"magnet export: watching vehicle {report.sysid}'s compass {instance} for {args.check_s:g} s", flush=True)
    done = after_apply(
        args.apply,
        args.baud,
        report.sysid,
        calibration,
        instance,
        before,
        after,
        rotation_in_force=args.rotation_in_force,
        do_reboot=args.reboot,
        check_s=args.check_s,
    )
    for line in done.lines():
        print(f"magnet export: {line}")
    return 3 if done.check is not None and done.check.agrees is False else 0
