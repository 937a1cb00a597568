"""``magnet report FILE.csv --calibration cal.json --out report.html|.png|.pdf``: a calibration report (a progress
bar on a terminal).

Shows the raw and calibrated field's projections (xy, xz, yz), |B| before and after, the sphere of directions with
the missing cells, the gate's figures and reason, and the heading error against the true heading when the samples
carry truth (``true_heading_deg``, as ``magnet sample --emulate`` writes it). FILE may also be an .npz recording
with ``mag_ut`` (and ``acc_ms2``) arrays.
"""

from __future__ import annotations

import argparse

from services.common.inputs import add_input_arguments
from services.common.inputs.input_options import InputOptions
from services.common.place import add_field_arguments, place
from services.common.records import load_calibration
from services.report.write import write_report


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("file", metavar="FILE.csv", help="the samples (CSV as for 'magnet fit', or an .npz recording)")
    parser.add_argument("--calibration", required=True, metavar="cal.json", help="a record as 'magnet fit' writes it")
    parser.add_argument("--out", required=True, metavar="report.html", help="where to write it (.html, .png or .pdf)")
    parser.add_argument("--unit", help="unit of the samples (default: the calibration's)")
    parser.add_argument(
        "--paper",
        choices=("a4", "letter"),
        default="a4",
        help="a PDF's paper size (default a4): a page with the "
        "record's id, date, method and coefficients, then the figure",
    )
    parser.add_argument(
        "--declination",
        type=float,
        metavar="DEG",
        help="declination for the heading error (default: from --location, else from the data)",
    )
    add_field_arguments(parser)
    add_input_arguments(parser)


def run(args: argparse.Namespace) -> int:
    declination, field = place(args)
    calibration = load_calibration(args.calibration)
    path = write_report(
        args.out,
        args.file,
        calibration,
        args.unit,
        declination,
        field,
        InputOptions.from_args(args),
        "report",
        args.paper,
    )
    print(f"magnet report: {path}")
    return 0
