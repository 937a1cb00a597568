"""Figures of merit of a calibration, computed on the corrected field (see the package docstring for each figure).

Pure numpy. ``assess`` returns a ``magnet.model.Quality``.
"""

from __future__ import annotations

import enum
import math
from typing import Any

import numpy as np

from magnet.model import Calibration, Quality
from magnet.quality.coverage import coverage, heading_coverage
from magnet.quality.stats import covariance
from magnet.units import ut_per_unit


class Geometry(enum.Enum):
    """What the samples are expected to cover, which decides how they are judged."""

    SPHERE = "sphere"  # all attitudes: |B| constant, directions over the whole sphere
    CIRCLE = "circle"  # a level turn: horizontal magnitude constant, headings all round
    TURNTABLE = "turntable"  # known attitudes on a turntable: |B| constant, coverage is not asked for


def scatter_condition(points: np.ndarray) -> float:
    """sqrt(largest / smallest eigenvalue) of the covariance of points (N, d); inf when they are degenerate."""
    points = np.asarray(points, dtype=float)
    if len(points) < 2:
        return math.inf
    eig = np.linalg.eigvalsh(covariance(points))
    if eig[0] <= eig[-1] * 1e-24 or eig[-1] <= 0:
        return math.inf
    return float(math.sqrt(eig[-1] / eig[0]))


def matrix_condition(matrix: np.ndarray) -> float:
    """Largest / smallest singular value of a matrix (the soft-iron eigenvalue ratio for a symmetric one)."""
    s = np.linalg.svd(np.asarray(matrix, dtype=float), compute_uv=False)
    return float(s[0] / s[-1]) if s[-1] > 0 else math.inf


def _magnitudes(corrected: np.ndarray, geometry: Geometry) -> np.ndarray:
    part = corrected[:, :2] if geometry is Geometry.CIRCLE else corrected
    return np.sqrt(np.einsum("ij,ij->i", part, part))


def _residuals(corrected: np.ndarray, reference: float, geometry: Geometry, to_ut: float | None) -> dict[str, Any]:
    rms = float(np.sqrt(np.mean((_magnitudes(corrected, geometry) - reference) ** 2)))
    return {
        "rms": rms,
        "rms_ut": rms * to_ut if to_ut is not None else None,
        "rms_pct": 100.0 * rms / reference if reference > 0 else math.inf,
    }


def dip_spread_deg(corrected: np.ndarray, acc: np.ndarray) -> float:
    """Standard deviation (deg) of the angle between field (N,3) and specific force (N,3); rows of zero are skipped."""
    nf = np.linalg.norm(corrected, axis=1)
    na = np.linalg.norm(acc, axis=1)
    keep = (nf > 0) & (na > 0)
    cosang = np.einsum("ij,ij->i", corrected[keep], acc[keep]) / (nf[keep] * na[keep])
    return float(np.degrees(np.arccos(np.clip(cosang, -1.0, 1.0))).std())


def assess(
    raw: np.ndarray,
    calibration: Calibration,
    *,
    geometry: Geometry | str = Geometry.SPHERE,
    acc: np.ndarray | None = None,
    expected_field_ut: float | None = None,
    fitted_radius_ut: float | None = None,
    holdout: tuple[np.ndarray, Calibration] | None = None,
    field_points_down: bool = True,
    corrected: np.ndarray | None = None,
) -> Quality:
    """Figures of merit of ``calibration`` on raw samples (N, 3) in its raw unit.

    acc: (N, 3) specific force, any unit, or None. expected_field_ut: |B| the site should show (WMM), uT.
    fitted_radius_ut: the fitted radius before any scaling to the expected field, uT (None when the raw unit has no
    uT scale). holdout: (raw_test (M, 3), calibration fitted without them), scored against its own field strength.
    Returns the ``Quality`` (its map: the keys listed in docs/interfaces.md plus ``geometry`` and ``residual_rms`` in
    the output unit). corrected: ``calibration.apply(raw)`` when the caller has it (None: computed here).
    """
    geometry = Geometry(geometry)
    raw = np.asarray(raw, dtype=float)
    corrected = calibration.apply(raw) if corrected is None else corrected
    to_ut = ut_per_unit(calibration.output_unit)
    res = _residuals(corrected, _reference(corrected, calibration, geometry), geometry, to_ut)
    cov = (
        heading_coverage(corrected)
        if geometry is Geometry.CIRCLE
        else coverage(corrected, field_points_down=field_points_down)
    )
    matrix = calibration.matrix[:2, :2] if geometry is Geometry.CIRCLE else calibration.matrix
    scatter = raw[:, :2] if geometry is Geometry.CIRCLE else raw
    held = _holdout_residuals(holdout, geometry, to_ut)
    return Quality(
        geometry=geometry.value,
        residual_rms=res["rms"],
        residual_rms_ut=res["rms_ut"],
        residual_rms_pct=res["rms_pct"],
        coverage=cov.fraction,
        cells_hit=cov.cells_hit,
        cell_count=cov.cell_count,
        missing_directions=tuple(cov.missing),
        radius=fitted_radius_ut,
        expected_field_ut=expected_field_ut,
        radius_ratio=(
            fitted_radius_ut / expected_field_ut if fitted_radius_ut is not None and expected_field_ut else None
        ),
        soft_iron_condition=matrix_condition(matrix),
        scatter_condition=scatter_condition(scatter) if len(raw) > scatter.shape[1] else math.inf,
        dip_spread_deg=(
            dip_spread_deg(corrected, np.asarray(acc, dtype=float))
            if acc is not None and geometry is not Geometry.CIRCLE
            else None
        ),
        holdout_rms_ut=held["rms_ut"],
        holdout_rms_pct=held["rms_pct"],
    )


def _holdout_residuals(
    holdout: tuple[np.ndarray, Calibration] | None, geometry: Geometry, to_ut: float | None
) -> dict[str, Any]:
    """Residuals of the held-out samples under the calibration fitted without them (None when there are none)."""
    if holdout is None or not len(holdout[0]):
        return {"rms_ut": None, "rms_pct": None}
    test_raw, train_cal = holdout
    test_corrected = train_cal.apply(np.asarray(test_raw, dtype=float))
    return _residuals(test_corrected, _reference(test_corrected, train_cal, geometry), geometry, to_ut)


def _reference(corrected: np.ndarray, calibration: Calibration, geometry: Geometry) -> float:
    """Magnitude the corrected samples should show: the record's field strength, else their mean."""
    if geometry is not Geometry.CIRCLE and calibration.field_strength > 0:
        return float(calibration.field_strength)
    return float(_magnitudes(corrected, geometry).mean())
