"""What a calibration report shows, computed from samples and a calibration (numpy only; drawing is in ``render``).

Shapes and units: raw (N, 3) in the calibration's raw unit, calibrated (N, 3) in its output unit, acc (N, 3) any unit
(directions only), angles in degrees.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Any

import numpy as np

from magnet.attitude import heading as hd
from magnet.model import Calibration
from magnet.quality import Geometry, assess, gate
from services.common.inputs import read_input, read_input_told
from services.common.inputs.csvio import SampleTable
from services.common.inputs.input_options import InputOptions

TRUTH_COLUMN = "true_heading_deg"  # what ``magnet sample --emulate`` writes
PITCH_COLUMN = "pitch_deg"
#: the most rows of an .npz recording's array (an hour at 500 Hz; 48 MB of float64 each)
MAX_NPZ_SAMPLES = 2_000_000
MAX_SCORED_PITCH_DEG = 70.0  # beyond this the heading of the x axis is poorly defined


@dataclasses.dataclass(frozen=True)
class Samples:
    """Samples of one recording: raw (N, 3) in ``unit``, acc (N, 3) or None, truth angles (N,) or None."""

    source: str
    raw: np.ndarray
    unit: str
    acc: np.ndarray | None = None
    true_heading_deg: np.ndarray | None = None
    pitch_deg: np.ndarray | None = None


@dataclasses.dataclass(frozen=True)
class HeadingErrors:
    """Heading against the truth: truth (M,), error after calibration (M,), error of the raw field (M,), degrees;
    ``note`` says how the declination was chosen."""

    truth_deg: np.ndarray
    error_deg: np.ndarray
    raw_error_deg: np.ndarray
    note: str

    @property
    def rms_deg(self) -> float:
        return float(np.sqrt(np.mean(self.error_deg**2)))

    @property
    def raw_rms_deg(self) -> float:
        return float(np.sqrt(np.mean(self.raw_error_deg**2)))


@dataclasses.dataclass(frozen=True)
class ReportData:
    """Everything drawn: the samples before and after, |B| spreads (std / mean, %), the gate's figures and verdict."""

    samples: Samples
    calibration: Calibration
    calibrated: np.ndarray
    quality: dict[str, Any]
    accepted: bool
    reason: str
    spread_before_pct: float
    spread_after_pct: float
    headings: HeadingErrors | None

    @property
    def geometry(self) -> Geometry:
        return Geometry.CIRCLE if self.calibration.method == "minmax2d" else Geometry.SPHERE


def load_samples(
    path: str | Path, unit: str | None, options: InputOptions | None = None, command: str | None = None
) -> Samples:
    """A CSV (``magnet fit``'s format, truth columns if present), a flight log (``options`` says which magnetometer;
    with ``command`` its note goes to stderr under that name) or a BROAD-style .npz (``mag_ut``, ``acc_ms2``)."""
    path = Path(path)
    if path.suffix.lower() == ".npz":
        mag, acc = _npz_arrays(path)
        keep = np.isfinite(mag).all(axis=1) & (np.isfinite(acc).all(axis=1) if acc is not None else True)
        return Samples(str(path), mag[keep], unit or "ut", None if acc is None else acc[keep])
    options = options or InputOptions()
    table = read_input_told(path, options, command) if command else read_input(path, options)
    return Samples(
        str(path), table.mag, unit or "ut", table.acc, _column(table, TRUTH_COLUMN), _column(table, PITCH_COLUMN)
    )


def _npz_arrays(path: Path) -> tuple[np.ndarray, np.ndarray | None]:
    """``mag_ut`` and ``acc_ms2`` (or None) of an .npz recording; ValueError naming the file for one that is not a
    zip numpy reads, an array that is not (N, 3) numbers, or that claims more than ``MAX_NPZ_SAMPLES`` rows or more
    bytes than its zip entry holds: each array's header is read before the array (a 2 MB file inflating to 2 GiB,
    or a header claiming 10^10 rows, made numpy allocate them)."""
    import zipfile

    try:
        with zipfile.ZipFile(path) as archive:
            for name in ("mag_ut.npy", "acc_ms2.npy"):
                if name in archive.namelist():
                    _check_npy(path, name, archive)
        with np.load(path, allow_pickle=False) as data:
            if "mag_ut" not in data.files:
                raise ValueError(f"{path}: an .npz recording needs a mag_ut array (N x 3, uT)")
            mag = np.asarray(data["mag_ut"], dtype=float)
            acc = np.asarray(data["acc_ms2"], dtype=float) if "acc_ms2" in data.files else None
    except (OSError, EOFError, zipfile.BadZipFile, ValueError) as exc:
        if isinstance(exc, ValueError) and str(exc).startswith(str(path)):
            raise
        raise ValueError(f"{path}: not an .npz recording numpy can read ({type(exc).__name__}: {exc})") from None
    return mag, acc


def _check_npy(path: Path, name: str, archive: Any) -> None:
    info = archive.getinfo(name)
    with archive.open(name) as member:
        version = np.lib.format.read_magic(member)
        if version not in ((1, 0), (2, 0)):
            raise ValueError(f"{path}: {name} is an .npy of version {version}; numpy writes 1.0 or 2.0")
        read = np.lib.format.read_array_header_1_0 if version == (1, 0) else np.lib.format.read_array_header_2_0
        shape, _, dtype = read(member)  # the header only
    rows = shape[0] if len(shape) == 2 and shape[1] == 3 else -1
    if rows < 0 or dtype.kind not in "iuf":
        raise ValueError(f"{path}: {name} must be an N x 3 array of numbers, not {shape} of {dtype}")
    if rows > MAX_NPZ_SAMPLES or rows * 3 * dtype.itemsize > info.file_size:
        raise ValueError(
            f"{path}: {name} claims {rows} rows (its zip entry holds {info.file_size} bytes; at most {MAX_NPZ_SAMPLES} "
            "rows): a damaged or crafted file"
        )


def _column(table: SampleTable, name: str) -> np.ndarray | None:
    return table.numeric(name) if name in table.columns else None


def spread_pct(vectors: np.ndarray, geometry: Geometry = Geometry.SPHERE) -> float:
    """std / mean of the magnitudes (of x, y only for a level turn), in %."""
    part = vectors[:, :2] if geometry is Geometry.CIRCLE else vectors
    norms = np.linalg.norm(part, axis=1)
    return float(100.0 * norms.std() / norms.mean()) if norms.size and norms.mean() > 0 else float("nan")


def build_report(
    samples: Samples,
    calibration: Calibration,
    declination_deg: float | None = None,
    expected_field_ut: float | None = None,
) -> ReportData:
    """The report's figures. The gate's figures are the record's own when it carries them (what the gate judged);
    otherwise they are computed on these samples and gated here."""
    if samples.unit != calibration.unit:
        raise ValueError(
            f"{samples.source} is in {samples.unit!r} but the calibration expects {calibration.unit!r}: "
            f"give --unit {calibration.unit}"
        )
    calibrated = calibration.apply(samples.raw)
    geometry = Geometry.CIRCLE if calibration.method == "minmax2d" else Geometry.SPHERE
    quality = calibration.quality.to_dict()
    accepted, reason = calibration.accepted, calibration.reason
    if not quality.get("residual_rms_pct"):
        assessed = assess(
            samples.raw, calibration, geometry=geometry, acc=samples.acc, expected_field_ut=expected_field_ut
        )
        accepted, reason = gate(assessed)
        quality = assessed.to_dict()
    return ReportData(
        samples,
        calibration,
        calibrated,
        quality,
        accepted,
        reason,
        spread_pct(samples.raw, geometry),
        spread_pct(calibrated, geometry),
        heading_errors(samples, calibrated, declination_deg),
    )


def heading_errors(samples: Samples, calibrated: np.ndarray, declination_deg: float | None) -> HeadingErrors | None:
    """Heading error against the truth column, when the samples carry one (None otherwise).

    Headings are tilt-compensated with the accelerometer (level headings without one); samples whose truth pitch
    exceeds ``MAX_SCORED_PITCH_DEG`` are left out. Without a declination, the circular mean difference between
    truth and the calibrated magnetic heading stands in for it (and the note says so)."""
    if samples.true_heading_deg is None:
        return None
    keep = np.ones(len(samples.raw), dtype=bool)
    if samples.pitch_deg is not None:
        keep &= np.abs(samples.pitch_deg) <= MAX_SCORED_PITCH_DEG
    if samples.acc is not None:
        acc = samples.acc[keep]
        magnetic = hd.tilt_compensated_heading_deg(calibrated[keep], acc)
        raw_magnetic = hd.tilt_compensated_heading_deg(samples.raw[keep], acc)
    else:
        magnetic, raw_magnetic = hd.level_heading_deg(calibrated[keep]), hd.level_heading_deg(samples.raw[keep])
    truth = samples.true_heading_deg[keep]
    if declination_deg is None:
        diff = np.radians(truth - magnetic)
        declination_deg = float(np.degrees(np.arctan2(np.sin(diff).mean(), np.cos(diff).mean())))
        note = f"declination {declination_deg:.2f} deg taken from the data (no --location or --declination given)"
    else:
        note = f"declination {declination_deg:.2f} deg"
    good = np.isfinite(magnetic) & np.isfinite(raw_magnetic)
    return HeadingErrors(
        truth[good],
        hd.angle_difference_deg(magnetic[good] + declination_deg, truth[good]),
        hd.angle_difference_deg(raw_magnetic[good] + declination_deg, truth[good]),
        note,
    )
