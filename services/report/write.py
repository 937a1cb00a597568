"""``write_report``: a calibration report from samples and a record, written as HTML, PNG or PDF; shared by
``magnet report`` and ``magnet fit --report``."""

from __future__ import annotations

import datetime
from pathlib import Path

from magnet.model import Calibration
from services.common.inputs.input_options import InputOptions
from services.report.formats import FORMATS


def write_report(
    out: str | Path,
    samples_path: str | Path,
    calibration: Calibration,
    unit: str | None,
    declination_deg: float | None,
    expected_field_ut: float | None,
    options: InputOptions | None = None,
    command: str | None = None,
    paper: str = "a4",
) -> Path:
    """Build and write the report of ``calibration`` on the samples in ``samples_path`` (``options``: which stream
    of a recording; ``command``: tell the user which, under that name; a PDF on ``paper``, a4 or letter); returns
    the file."""
    out = Path(out)
    if out.suffix.lower() not in FORMATS:  # refuse before any work, and before matplotlib is imported
        raise ValueError(f"report {out}: the file must end in {', '.join(FORMATS)}")
    from services.common.progress import steps
    from services.report.data import build_report, load_samples
    from services.report.render import write

    with steps(["report: reading samples", "report: assessing the fit", "report: drawing"]) as step:
        step("report: reading samples")
        samples = load_samples(samples_path, unit or calibration.unit, options, command)
        step("report: assessing the fit")
        data = build_report(samples, calibration, declination_deg, expected_field_ut)
        step("report: drawing")
        created = datetime.datetime.now(datetime.UTC).strftime("%Y-%m-%d %H:%M UTC")
        write(out, data, paper, created)
    return out
