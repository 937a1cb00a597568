"""Drawing a calibration report with matplotlib (no display): one figure, saved as PNG, as PDF (matplotlib's PDF
backend) or inside an HTML page.

Panels: the raw field's projections (xy, xz, yz), the calibrated field's (with the expected radius), |B| before and
after, the sphere of directions (equal-area map: the 100 cells of ``magnet.quality``, covered or missing), the
heading error against the true heading when the samples carry truth, and the gate's figures and reason.
"""

from __future__ import annotations

import base64
import html
import io
import json
import math
from pathlib import Path
from typing import Any

import numpy as np
from matplotlib.figure import Figure
from matplotlib.text import Text

from magnet.quality import fibonacci_centres
from services.report.data import ReportData
from services.report.formats import FORMATS

MAX_POINTS = 6000
#: samples whose nearest direction cell is found at once (the sphere's map): 16,384 x 100 cells, 13 MB
HIT_ROWS = 16_384
PAIRS = ((0, 1, "x", "y"), (0, 2, "x", "z"), (1, 2, "y", "z"))
RAW_COLOUR, CAL_COLOUR, BAD_COLOUR = "#e4572e", "#1f77b4", "#bbbbbb"


def _thin(points: np.ndarray) -> np.ndarray:
    return points[:: max(1, math.ceil(len(points) / MAX_POINTS))]


def _projections(
    fig: Figure, grid: Any, row: int, points: np.ndarray, colour: str, unit: str, radius: float | None, label: str
) -> None:
    pts = _thin(points)
    for col, (i, j, a, b) in enumerate(PAIRS):
        ax = fig.add_subplot(grid[row, col])
        ax.scatter(pts[:, i], pts[:, j], s=2, c=colour, alpha=0.5, linewidths=0, rasterized=True)
        if radius:
            t = np.linspace(0, 2 * np.pi, 361)
            ax.plot(radius * np.cos(t), radius * np.sin(t), color="#333333", lw=0.8, ls="--")
        ax.axhline(0, color="#999999", lw=0.5)
        ax.axvline(0, color="#999999", lw=0.5)
        ax.set_aspect("equal", adjustable="datalim")
        shown = "µT" if unit == "ut" else unit
        ax.set_xlabel(f"{a} ({shown})")
        ax.set_ylabel(f"{b} ({shown})")
        ax.set_title(f"{label}: {a}{b}", fontsize=10)
        ax.grid(alpha=0.25)


def _series(ax: Any, x: np.ndarray, y: np.ndarray, colour: str, label: str, size: float) -> None:
    """One series of dots (x, y of shape (N,)), thinned to at most about MAX_POINTS."""
    ax.plot(_thin(x), _thin(y), ".", ms=size, color=colour, label=label, rasterized=True)


def _magnitudes(fig: Figure, cell: Any, data: ReportData) -> None:
    ax = fig.add_subplot(cell)
    before = np.linalg.norm(data.samples.raw, axis=1)
    after = np.linalg.norm(data.calibrated, axis=1)
    index = np.arange(len(before))
    _series(ax, index, 100 * before / before.mean(), RAW_COLOUR, f"raw: spread {data.spread_before_pct:.2f} %", 1.5)
    _series(ax, index, 100 * after / after.mean(), CAL_COLOUR, f"calibrated: spread {data.spread_after_pct:.2f} %", 1.5)
    ax.axhline(100, color="#333333", lw=0.8)
    ax.set_xlabel("sample")
    ax.set_ylabel("|B| in % of its mean")
    ax.set_title("|B| before and after (spread = std / mean)", fontsize=10)
    ax.legend(loc="upper right", fontsize=8, markerscale=6)
    ax.grid(alpha=0.25)


def _coverage(fig: Figure, cell: Any, data: ReportData) -> None:
    """Equal-area map of directions: azimuth around body z against z (Lambert cylindrical)."""
    ax = fig.add_subplot(cell)
    centres = fibonacci_centres()
    field = data.calibrated
    unit = field / np.maximum(np.linalg.norm(field, axis=1, keepdims=True), 1e-300)
    hit = np.zeros(len(centres), dtype=bool)
    for lo in range(0, len(unit), HIT_ROWS):  # (rows x cells) at a time: 800 bytes a sample at once for 8M samples
        hit[np.unique(np.argmax(unit[lo : lo + HIT_ROWS] @ centres.T, axis=1))] = True
    pts = _thin(unit)
    azimuth = lambda v: np.degrees(np.arctan2(v[:, 1], v[:, 0])) % 360  # noqa: E731
    ax.scatter(azimuth(pts), pts[:, 2], s=1, c=CAL_COLOUR, alpha=0.25, linewidths=0, rasterized=True)
    ax.scatter(
        azimuth(centres[hit]),
        centres[hit, 2],
        s=60,
        facecolors="none",
        edgecolors="#2ca02c",
        lw=1.4,
        label=f"covered ({hit.sum()})",
    )
    ax.scatter(azimuth(centres[~hit]), centres[~hit, 2], s=60, c=RAW_COLOUR, label=f"missing ({(~hit).sum()})")
    ax.set_xticks([0, 90, 180, 270, 360], ["+x", "+y", "-x", "-y", "+x"])
    ax.set_yticks([-1, 0, 1], ["-z (up)", "0", "+z (down)"])
    ax.set_xlim(-5, 365)
    ax.set_ylim(-1.1, 1.25)
    missing = data.quality.get("missing_directions") or []
    ax.set_title("sphere of field directions" + (f"\nmissing: {'; '.join(missing)}" if missing else ""), fontsize=9)
    ax.legend(loc="upper center", ncol=2, fontsize=8, frameon=False)


def _headings(fig: Figure, cell: Any, data: ReportData) -> None:
    ax = fig.add_subplot(cell)
    errors = data.headings
    if errors is None:
        ax.text(
            0.5,
            0.5,
            "no truth column (true_heading_deg) in the samples:\nno heading error to show",
            ha="center",
            va="center",
            transform=ax.transAxes,
            color="#666666",
        )
        ax.set_axis_off()
        return
    _series(ax, errors.truth_deg, errors.raw_error_deg, RAW_COLOUR, f"raw field: RMS {errors.raw_rms_deg:.2f} deg", 2)
    _series(ax, errors.truth_deg, errors.error_deg, CAL_COLOUR, f"calibrated: RMS {errors.rms_deg:.2f} deg", 2)
    ax.axhline(0, color="#333333", lw=0.8)
    ax.set_xlim(0, 360)
    ax.set_xticks(range(0, 361, 45))
    ax.set_xlabel("true heading (deg)")
    ax.set_ylabel("heading error (deg)")
    ax.set_title(f"heading error against angle ({errors.note})", fontsize=9)
    ax.legend(loc="upper right", fontsize=8, markerscale=5)
    ax.grid(alpha=0.25)


def gate_lines(data: ReportData) -> list[tuple[str, str]]:
    """(name, value) of the gate's figures, for the figure and the HTML table."""
    q = data.quality

    def num(key: str, fmt: str, suffix: str = "") -> str:
        value = q.get(key)
        return "-" if value is None or not isinstance(value, (int, float)) else format(value, fmt) + suffix

    return [
        ("verdict", "accepted" if data.accepted else "rejected"),
        ("method", data.calibration.method),
        ("samples", str(len(data.samples.raw))),
        ("residual RMS", f"{num('residual_rms_ut', '.3f', ' uT')} ({num('residual_rms_pct', '.2f', ' %')})"),
        ("held-out RMS", f"{num('holdout_rms_ut', '.3f', ' uT')} ({num('holdout_rms_pct', '.2f', ' %')})"),
        ("coverage", num("coverage", ".0%")),
        ("radius / WMM", num("radius_ratio", ".3f")),
        ("soft-iron condition", num("soft_iron_condition", ".2f")),
        ("scatter condition", num("scatter_condition", ".2f")),
        ("dip spread", num("dip_spread_deg", ".2f", " deg")),
        ("|B| spread before", f"{data.spread_before_pct:.2f} %"),
        ("|B| spread after", f"{data.spread_after_pct:.2f} %"),
    ]


def _gate_panel(fig: Figure, cell: Any, data: ReportData) -> None:
    ax = fig.add_subplot(cell)
    ax.set_axis_off()
    colour = "#2ca02c" if data.accepted else "#d62728"
    ax.text(0, 1, "quality gate", fontsize=11, weight="bold", va="top", transform=ax.transAxes)
    for k, (name, value) in enumerate(gate_lines(data)):
        y = 0.9 - k * 0.062
        ax.text(0, y, name, fontsize=9, va="top", transform=ax.transAxes)
        ax.text(
            0.55,
            y,
            value,
            fontsize=9,
            va="top",
            transform=ax.transAxes,
            color=colour if name == "verdict" else "black",
            weight="bold" if name == "verdict" else "normal",
        )
    wrapped = _wrap(data.reason, 48)
    ax.text(0, 0.9 - 12 * 0.062 - 0.02, wrapped, fontsize=8, va="top", transform=ax.transAxes, color="#444444")


def _wrap(text: str, width: int) -> str:
    words, lines, line = text.split(), [], ""
    for word in words:
        if len(line) + len(word) + 1 > width:
            lines.append(line)
            line = word
        else:
            line = f"{line} {word}".strip()
    return "\n".join([*lines, line][:6])


def figure(data: ReportData) -> Figure:
    """The whole report as one matplotlib figure (4 rows x 3 columns)."""
    fig = Figure(figsize=(16, 19), dpi=90, layout="constrained")
    grid = fig.add_gridspec(4, 3)
    cal = data.calibration
    fig.suptitle(
        f"{Path(data.samples.source).name}: {cal.method} calibration, {'accepted' if data.accepted else 'rejected'}",
        fontsize=14,
        weight="bold",
    )
    _projections(fig, grid, 0, data.samples.raw, RAW_COLOUR, data.samples.unit, None, "raw")
    radius = cal.field_strength or float(np.linalg.norm(data.calibrated, axis=1).mean())
    _projections(fig, grid, 1, data.calibrated, CAL_COLOUR, cal.output_unit, radius, "calibrated")
    _magnitudes(fig, grid[2, :2], data)
    _coverage(fig, grid[2, 2], data)
    _headings(fig, grid[3, :2], data)
    _gate_panel(fig, grid[3, 2], data)
    return fig


def png_bytes(data: ReportData) -> bytes:
    buffer = io.BytesIO()
    figure(data).savefig(buffer, format="png")
    return buffer.getvalue()


#: paper sizes of the PDF report, inches (portrait)
PAPERS = {"a4": (8.27, 11.69), "letter": (8.5, 11.0)}


def summary_lines(data: ReportData, created: str) -> list[tuple[str, str]]:
    """The first page's rows: what the record is (id, date, method, verdict), its coefficients with their units, and
    the gate's figures."""
    cal = data.calibration
    rows = [
        ("calibration id", cal.content_id),
        ("report made", created),
        ("samples", f"{Path(data.samples.source).name} ({len(data.samples.raw)} samples)"),
        ("method", cal.method),
        ("verdict", "accepted" if data.accepted else "rejected"),
        ("field strength", f"{cal.field_strength:.3f} {cal.output_unit}"),
        ("offset b", "  ".join(f"{v:+.4f}" for v in cal.offset) + f"  {cal.unit}"),
    ]
    rows += [("matrix A" if k == 0 else "", "  ".join(f"{v:+.6f}" for v in row)) for k, row in enumerate(cal.matrix)]
    rows.append(("correction", f"B = A (u - b): u raw ({cal.unit}), B corrected ({cal.output_unit})"))
    return rows + [(name, value) for name, value in gate_lines(data) if name not in ("verdict", "method", "samples")]


def _summary_page(data: ReportData, size_in: tuple[float, float], created: str) -> Figure:
    fig = Figure(figsize=size_in)
    name = Path(data.samples.source).name
    fig.text(0.08, 0.95, f"magnet calibration report: {name}", fontsize=14, weight="bold", va="top")
    y = 0.90
    for label, value in summary_lines(data, created):
        fig.text(0.08, y, label, fontsize=9, va="top", weight="bold")
        fig.text(0.32, y, value, fontsize=9, va="top", family="monospace")
        y -= 0.024
    fig.text(0.08, y - 0.01, "reason", fontsize=9, va="top", weight="bold")
    fig.text(0.32, y - 0.01, _wrap(data.reason, 70), fontsize=9, va="top", color="#444444")
    return fig


def pdf_bytes(data: ReportData, paper: str = "a4", created: str = "") -> bytes:
    """The report on ``paper`` (``PAPERS``): a page with the record's id, date, method, coefficients and the gate's
    figures, then the figure scaled to the page (matplotlib's PDF backend: vector drawing, text kept as text); the
    gate's figures and the reason also in the document's metadata."""
    from matplotlib.backends.backend_pdf import PdfPages

    if paper not in PAPERS:
        raise ValueError(f"--paper {paper}: choose one of {', '.join(PAPERS)}")
    size_in = PAPERS[paper]
    buffer = io.BytesIO()
    subject = "; ".join(f"{k}: {v}" for k, v in gate_lines(data))
    metadata = {"Title": f"magnet report: {Path(data.samples.source).name}", "Subject": subject}
    with PdfPages(buffer, metadata=metadata) as pages:
        pages.savefig(_summary_page(data, size_in, created))
        drawing = figure(data)
        drawing.set_size_inches(*size_in)
        drawing.set_dpi(72)
        for text in drawing.findobj(Text):
            text.set_fontsize(max(4.0, float(text.get_fontsize()) * 0.55))  # the 16 x 19 inch figure on the page
        pages.savefig(drawing)
    return buffer.getvalue()


def html_page(data: ReportData) -> str:
    """A self-contained page: the figure (embedded PNG), the gate's figures and the calibration record."""
    image = base64.b64encode(png_bytes(data)).decode()
    rows = "".join(f"<tr><th>{html.escape(k)}</th><td>{html.escape(v)}</td></tr>" for k, v in gate_lines(data))
    verdict = "accepted" if data.accepted else "rejected"
    record = html.escape(json.dumps(data.calibration.to_dict(), indent=2))
    name = html.escape(Path(data.samples.source).name)
    return f"""<!doctype html>
<html lang="en"><head><meta charset="utf-8"><title>magnet report: {name}</title>
<style>body{{font-family:system-ui,sans-serif;margin:24px;color:#222;max-width:1500px}}
table{{border-collapse:collapse}}th,td{{text-align:left;padding:3px 12px;border-bottom:1px solid #ddd}}
.accepted{{color:#2ca02c}}.rejected{{color:#d62728}}img{{width:100%;max-width:1440px}}
pre{{background:#f5f5f5;padding:10px;overflow:auto}}</style></head>
<body><h1>{name}: {html.escape(data.calibration.method)} calibration, <span class="{verdict}">{verdict}</span></h1>
<p>{html.escape(data.reason)}</p>
<table>{rows}</table>
<p><img alt="raw and calibrated field, |B|, sphere of directions, heading error"
  src="data:image/png;base64,{image}"></p>
<h2>Calibration record</h2><pre>{record}</pre>
</body></html>
"""


def write(path: Path, data: ReportData, paper: str = "a4", created: str = "") -> None:
    """Write the report as ``.png``, ``.html`` or ``.pdf`` (by the file's suffix; a PDF on ``paper``, saying it was
    made at ``created``)."""
    suffix = path.suffix.lower()
    if suffix not in FORMATS:
        raise ValueError(f"report {path}: the file must end in {', '.join(FORMATS)}")
    if suffix == ".png":
        content = png_bytes(data)
    elif suffix == ".pdf":
        content = pdf_bytes(data, paper, created)
    else:
        content = html_page(data).encode()
    tmp = path.with_name(f".{path.name}.tmp")
    tmp.write_bytes(content)
    tmp.replace(path)
