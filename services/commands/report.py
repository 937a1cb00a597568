"""``magnet report FILE.csv --calibration cal.json --out report.html|.png|.pdf``: a calibration report (a progress
bar on a terminal).

Shows the raw and calibrated field's projections (xy, xz, yz), |B| before and after, the sphere of directions with
the missing cells, the gate's figures and reason, and the heading error against the true heading when the samples
carry truth (``true_heading_deg``, as ``magnet sample --emulate`` writes it). FILE may also be an .npz recording
with ``mag_ut`` (and ``acc_ms2``) arrays.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from magnet.geomag import earth_field, parse_location
from magnet.model import Calibration
from services.commands.fit import add_field_arguments, load_calibration
from services.common.inputs import InputOptions, add_input_arguments


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("file", metavar="FILE.csv", help="the samples (CSV as for 'magnet fit', or an .npz recording)")
    parser.add_argument("--calibration", required=True, metavar="cal.json", help="a record as 'magnet fit' writes it")
    parser.add_argument("--out", required=True, metavar="report.html", help="where to write it (.html, .png or .pdf)")
    parser.add_argument("--unit", help="unit of the samples (default: the calibration's)")
    parser.add_argument(
        "--declination",
        type=float,
        metavar="DEG",
        help="declination for the heading error (default: from --location, else from the data)",
    )
    add_field_arguments(parser)
    add_input_arguments(parser)


def place(args: argparse.Namespace) -> tuple[float | None, float | None]:
    """(declination deg, expected field uT) from --declination or --location/--date, each None when not given."""
    if getattr(args, "declination", None) is not None and args.location:
        raise ValueError("give either --declination or --location, not both")
    if args.location:
        field = earth_field(*parse_location(args.location), args.date)
        return field.declination_deg, field.total_ut
    if args.date:
        raise ValueError("--date needs --location")
    return getattr(args, "declination", None), None


def write_report(
    out: str | Path,
    samples_path: str | Path,
    calibration: Calibration,
    unit: str | None,
    declination_deg: float | None,
    expected_field_ut: float | None,
    options: InputOptions | None = None,
    command: str | None = None,
) -> Path:
    """Build and write the report of ``calibration`` on the samples in ``samples_path`` (``options``: which stream
    of a recording; ``command``: tell the user which, under that name); returns the file."""
    from services.common.progress import steps
    from services.report.data import build_report, load_samples
    from services.report.render import FORMATS, write

    out = Path(out)
    if out.suffix.lower() not in FORMATS:  # refuse before any work
        raise ValueError(f"report {out}: the file must end in {', '.join(FORMATS)}")
    with steps(["report: reading samples", "report: assessing the fit", "report: drawing"]) as step:
        step("report: reading samples")
        samples = load_samples(samples_path, unit or calibration.unit, options, command)
        step("report: assessing the fit")
        data = build_report(samples, calibration, declination_deg, expected_field_ut)
        step("report: drawing")
        write(out, data)
    return out


def run(args: argparse.Namespace) -> int:
    declination, field = place(args)
    calibration = load_calibration(args.calibration)
    path = write_report(
        args.out, args.file, calibration, args.unit, declination, field, InputOptions.from_args(args), "report"
    )
    print(f"magnet report: {path}")
    return 0
