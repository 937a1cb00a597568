"""Figures of merit of a calibration and the gate that accepts or refuses it (DESIGN.md section 3, "Quality").

Pure numpy. Every figure is computed on the corrected field ``calibration.apply(raw)``:

- residual: RMS over the samples of ``|B| - F``, where F is the expected magnitude (the record's ``field_strength``,
  or the mean ``|B|`` when that is 0); in uT when the output unit converts to uT, and in % of F. For the ``circle``
  geometry (a level turn, ``minmax2d``) the horizontal magnitude ``sqrt(Bx^2 + By^2)`` is judged instead of ``|B|``.
- coverage: the fraction of ~100 equal-area cells of the unit sphere (a Fibonacci lattice of cell centres; a sample
  belongs to its nearest centre) that hold at least one corrected field direction, and the empty cells named as the
  attitude a person should add. For the circle geometry: the fraction of 36 ten-degree heading sectors.
- radius: the fitted radius in uT (when the raw unit converts to uT) against the expected field (WMM), as a ratio.
- conditioning: ``soft_iron_condition`` = largest / smallest singular value of the correction matrix;
  ``scatter_condition`` = sqrt(largest / smallest eigenvalue) of the raw samples' covariance (the ratio of the
  widest to the thinnest spread of the cloud: ~1-3 for a tumbled sensor, large when the samples lie in a plane).
- dip spread: standard deviation, in degrees, of the angle between the corrected field and gravity (needs acc).
- held-out residual: the same residual for samples the fit did not see (the caller fits on one part, scores here).
"""

from __future__ import annotations

import dataclasses
import enum
import math
from collections import Counter
from typing import Any, Mapping

import numpy as np

from magnet.model import Calibration
from magnet.quality.motion import check_consistency
from magnet.units import UT_PER_UNIT, FieldUnit

CELL_COUNT = 100
HEADING_SECTORS = 36


class Geometry(enum.Enum):
    """What the samples are expected to cover, which decides how they are judged."""

    SPHERE = "sphere"  # all attitudes: |B| constant, directions over the whole sphere
    CIRCLE = "circle"  # a level turn: horizontal magnitude constant, headings all round
    TURNTABLE = "turntable"  # known attitudes on a turntable: |B| constant, coverage is not asked for


def ut_per_unit(unit: str) -> float | None:
    """uT per one raw unit, or None when the unit has no known scale (``counts``, free words)."""
    aliases = {"gamma": "nt", "g": "gauss", "microtesla": "ut", "µt": "ut", "uT": "ut"}
    name = aliases.get(unit.strip().lower(), unit.strip().lower())
    try:
        return UT_PER_UNIT[FieldUnit(name)]
    except ValueError:
        return None


def fibonacci_centres(count: int = CELL_COUNT) -> np.ndarray:
    """Centres of ``count`` near-equal-area cells on the unit sphere (Fibonacci lattice), shape (count, 3)."""
    i = np.arange(count) + 0.5
    z = 1.0 - 2.0 * i / count
    phi = math.pi * (3.0 - math.sqrt(5.0)) * i
    r = np.sqrt(1.0 - z * z)
    return np.column_stack([r * np.cos(phi), r * np.sin(phi), z])


_CENTRES = fibonacci_centres()

#: (axis, sign) of the body axis the field points along -> what a person does to get there. The Earth field dips
#: downward in the northern hemisphere (steeply, away from the equator), so "field along body +x" is reached by
#: pointing the nose down; in the southern hemisphere every phrase is flipped (``field_points_down=False``).
_ADVICE: dict[tuple[int, int], str] = {
    (0, 1): "point the nose (x) down",
    (0, -1): "point the nose (x) up",
    (1, 1): "roll right side (y) down",
    (1, -1): "roll left side down",
    (2, 1): "hold it level, top up",
    (2, -1): "turn it upside down",
}
MAX_ADVICE = 3


@dataclasses.dataclass(frozen=True)
class Coverage:
    """How much of the sphere (or of the turn) the samples cover.

    fraction: cells_hit / cell_count in [0, 1]; missing: at most a few phrases, most needed first.
    """

    fraction: float
    cells_hit: int
    cell_count: int
    missing: tuple[str, ...]


def _unit_rows(vectors: np.ndarray) -> np.ndarray:
    norms = np.linalg.norm(vectors, axis=1)
    keep = norms > 0
    return vectors[keep] / norms[keep, None]


def coverage(directions: np.ndarray, *, field_points_down: bool = True) -> Coverage:
    """Coverage of the sphere by field directions (N, 3) (any length; zero rows ignored), body frame.

    Missing cells are named by the dominant body axis of their centre, mapped to an attitude (see ``_ADVICE``),
    grouped and ordered by how many cells each phrase would fill.
    """
    unit = _unit_rows(np.asarray(directions, dtype=float).reshape(-1, 3))
    hit = np.zeros(len(_CENTRES), dtype=bool)
    if len(unit):
        hit[np.unique(np.argmax(unit @ _CENTRES.T, axis=1))] = True
    empty = _CENTRES[~hit] * (1.0 if field_points_down else -1.0)
    axes = np.argmax(np.abs(empty), axis=1)
    signs = np.sign(empty[np.arange(len(empty)), axes]).astype(int)
    counts = Counter(_ADVICE[(int(a), int(s))] for a, s in zip(axes, signs))
    missing = tuple(phrase for phrase, _ in counts.most_common(MAX_ADVICE))
    return Coverage(float(hit.mean()), int(hit.sum()), len(_CENTRES), missing)


def heading_coverage(field_xy: np.ndarray) -> Coverage:
    """Coverage of a level turn: 36 ten-degree sectors of heading, from the horizontal field (N, 2) or (N, 3).

    The heading of a level device whose horizontal field reads (x, y) is atan2(-y, x) (clockwise from magnetic north);
    missing sectors are merged into ranges ("turn to headings 90-150 deg").
    """
    xy = np.asarray(field_xy, dtype=float)[:, :2]
    heading = np.degrees(np.arctan2(-xy[:, 1], xy[:, 0])) % 360.0
    sector_deg = 360.0 / HEADING_SECTORS
    hit = np.zeros(HEADING_SECTORS, dtype=bool)
    hit[np.unique((heading // sector_deg).astype(int) % HEADING_SECTORS)] = True
    ranges = _empty_ranges(hit, sector_deg)
    missing = tuple(f"turn to headings {lo:.0f}-{hi:.0f} deg" for lo, hi in ranges[:MAX_ADVICE])
    return Coverage(float(hit.mean()), int(hit.sum()), HEADING_SECTORS, missing)


def _empty_ranges(hit: np.ndarray, sector_deg: float) -> list[tuple[float, float]]:
    """Runs of empty sectors (wrapping round 360) as (start_deg, end_deg), longest first."""
    n = len(hit)
    if hit.all():
        return []
    if not hit.any():
        return [(0.0, 360.0)]
    start = int(np.argmax(hit))  # begin scanning at a hit sector so that runs do not straddle the scan start
    runs, run_start = [], None
    for k in range(1, n + 1):
        idx = (start + k) % n
        if not hit[idx] and run_start is None:
            run_start = start + k
        elif hit[idx] and run_start is not None:
            runs.append((run_start, start + k))
            run_start = None
    runs.sort(key=lambda r: r[0] - r[1])
    return [((a % n) * sector_deg, ((b % n) * sector_deg) or 360.0) for a, b in runs]


def scatter_condition(points: np.ndarray) -> float:
    """sqrt(largest / smallest eigenvalue) of the covariance of points (N, d); inf when they are degenerate."""
    points = np.asarray(points, dtype=float)
    eig = np.linalg.eigvalsh(np.cov(points, rowvar=False))
    if eig[0] <= eig[-1] * 1e-24 or eig[-1] <= 0:
        return math.inf
    return float(math.sqrt(eig[-1] / eig[0]))


def matrix_condition(matrix: np.ndarray) -> float:
    """Largest / smallest singular value of a matrix (the soft-iron eigenvalue ratio for a symmetric one)."""
    s = np.linalg.svd(np.asarray(matrix, dtype=float), compute_uv=False)
    return float(s[0] / s[-1]) if s[-1] > 0 else math.inf


def _magnitudes(corrected: np.ndarray, geometry: Geometry) -> np.ndarray:
    part = corrected[:, :2] if geometry is Geometry.CIRCLE else corrected
    return np.linalg.norm(part, axis=1)


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
) -> dict[str, Any]:
    """Figures of merit of ``calibration`` on raw samples (N, 3) in its raw unit.

    acc: (N, 3) specific force, any unit, or None. expected_field_ut: |B| the site should show (WMM), uT.
    fitted_radius_ut: the fitted radius before any scaling to the expected field, uT (None when the raw unit has no
    uT scale). holdout: (raw_test (M, 3), calibration fitted without them), scored against its own field strength.
    Returns a JSON-able dict with the keys listed in docs/interfaces.md plus ``geometry`` and ``residual_rms`` (in
    the output unit).
    """
    geometry = Geometry(geometry)
    raw = np.asarray(raw, dtype=float)
    corrected = calibration.apply(raw)
    to_ut = ut_per_unit(calibration.output_unit)
    reference = _reference(corrected, calibration, geometry)
    res = _residuals(corrected, reference, geometry, to_ut)
    cov = heading_coverage(corrected) if geometry is Geometry.CIRCLE else coverage(
        corrected, field_points_down=field_points_down)
    matrix = calibration.matrix[:2, :2] if geometry is Geometry.CIRCLE else calibration.matrix
    scatter = raw[:, :2] if geometry is Geometry.CIRCLE else raw
    figures: dict[str, Any] = {
        "geometry": geometry.value,
        "residual_rms": res["rms"],
        "residual_rms_ut": res["rms_ut"],
        "residual_rms_pct": res["rms_pct"],
        "coverage": cov.fraction,
        "cells_hit": cov.cells_hit,
        "cell_count": cov.cell_count,
        "missing_directions": list(cov.missing),
        "radius": fitted_radius_ut,
        "expected_field_ut": expected_field_ut,
        "radius_ratio": (fitted_radius_ut / expected_field_ut
                         if fitted_radius_ut is not None and expected_field_ut else None),
        "soft_iron_condition": matrix_condition(matrix),
        "scatter_condition": scatter_condition(scatter) if len(raw) > scatter.shape[1] else math.inf,
        "dip_spread_deg": (dip_spread_deg(corrected, np.asarray(acc, dtype=float))
                           if acc is not None and geometry is not Geometry.CIRCLE else None),
        "holdout_rms_ut": None,
        "holdout_rms_pct": None,
    }
    if holdout is not None and len(holdout[0]):
        test_raw, train_cal = holdout
        test_corrected = train_cal.apply(np.asarray(test_raw, dtype=float))
        held = _residuals(test_corrected, _reference(test_corrected, train_cal, geometry), geometry, to_ut)
        figures["holdout_rms_ut"], figures["holdout_rms_pct"] = held["rms_ut"], held["rms_pct"]
    return figures


def _reference(corrected: np.ndarray, calibration: Calibration, geometry: Geometry) -> float:
    """Magnitude the corrected samples should show: the record's field strength, else their mean."""
    if geometry is not Geometry.CIRCLE and calibration.field_strength > 0:
        return float(calibration.field_strength)
    return float(_magnitudes(corrected, geometry).mean())


@dataclasses.dataclass(frozen=True)
class GateThresholds:
    """Limits a calibration must meet to be published.

    max_residual_ut / max_residual_pct: RMS of |B| - expected; 1.6 uT is ArduPilot's default fitness gate (16 mG),
    3.5 % NXP's best grade. Both apply where known (pct always, uT when the output unit converts to uT).
    max_circle_residual_pct: the same in % for a level turn (minmax2d), judged on the horizontal magnitude: a
    residual of e % there bends headings by up to about e/100 rad, so 5 % keeps them within ~3 deg (seed 001 reports
    under 4.5 deg for min/max compensation).
    max_holdout_factor: the held-out residual may exceed the limits above by this factor (it is noisier).
    min_coverage: fraction of sphere cells hit, for whole-sphere methods (60 %: a tumble by hand reaches 90 %+;
    below ~60 % an ellipsoid is extrapolated, not measured). min_heading_coverage: fraction of the level turn.
    radius_tolerance_pct: fitted radius vs the expected field (WMM), when both are known.
    max_soft_iron_condition: axis ratio of the correction; real sensors reach ~2.5, beyond 5 is a magnet or a bug.
    max_scatter_condition: thinnest spread of the raw cloud vs its widest; beyond this the samples are coplanar.
    max_dip_spread_deg: spread of the field-gravity angle after calibration, when acc is given.
    """

    max_residual_ut: float = 1.6
    max_residual_pct: float = 3.5
    max_circle_residual_pct: float = 5.0
    max_holdout_factor: float = 1.5
    min_coverage: float = 0.6
    min_heading_coverage: float = 0.75
    radius_tolerance_pct: float = 15.0
    max_soft_iron_condition: float = 5.0
    max_scatter_condition: float = 10.0
    max_dip_spread_deg: float = 5.0


def _num(quality: Mapping[str, Any], key: str) -> float | None:
    value = quality.get(key)
    return None if value is None else float(value)


def _check_scatter(q: Mapping[str, Any], t: GateThresholds) -> str | None:
    value = _num(q, "scatter_condition")
    if value is None or value <= t.max_scatter_condition:
        return None
    if q.get("geometry") == Geometry.CIRCLE.value:
        return f"samples lie on a line (scatter condition {value:.3g}): turn the device through a full circle"
    return (f"samples are coplanar (scatter condition {value:.3g} > {t.max_scatter_condition:g}): a level turn cannot "
            "give a 3D fit; tumble the device through all attitudes, or use minmax2d for level use")


def _check_coverage(q: Mapping[str, Any], t: GateThresholds) -> str | None:
    geometry = q.get("geometry", Geometry.SPHERE.value)
    limit = {Geometry.SPHERE.value: t.min_coverage, Geometry.CIRCLE.value: t.min_heading_coverage}.get(geometry)
    value = _num(q, "coverage")
    if limit is None or value is None or value >= limit:
        return None
    advice = ", ".join(q.get("missing_directions") or ()) or "move through more attitudes"
    return f"coverage {100 * value:.0f} % < {100 * limit:.0f} %: {advice}"


def _check_residual(q: Mapping[str, Any], t: GateThresholds) -> str | None:
    return _residual_reason(q, t, "residual_rms", 1.0, "residual")


def _check_holdout(q: Mapping[str, Any], t: GateThresholds) -> str | None:
    return _residual_reason(q, t, "holdout_rms", t.max_holdout_factor, "held-out residual")


#: what to do about a large residual, by geometry
_RESIDUAL_ADVICE: dict[str, str] = {
    Geometry.SPHERE.value: "keep magnets and metal away, move slowly, and check the sensor is not saturating",
    Geometry.CIRCLE.value: ("the turn is not a circle after min/max scaling (a tilted ellipse from cross-axis soft "
                            "iron, or the device tilted while turning): keep it level, or tumble it and use ellipsoid"),
    Geometry.TURNTABLE.value: ("the readings do not fit one linear model: check the mountings, the table angles and "
                               "the field components"),
}


def _residual_reason(q: Mapping[str, Any], t: GateThresholds, prefix: str, factor: float, name: str) -> str | None:
    ut, pct = _num(q, f"{prefix}_ut"), _num(q, f"{prefix}_pct")
    advice = _RESIDUAL_ADVICE.get(q.get("geometry", Geometry.SPHERE.value), _RESIDUAL_ADVICE["sphere"])
    if ut is not None and ut > factor * t.max_residual_ut:
        return f"{name} {ut:.2f} uT > {factor * t.max_residual_ut:.2f} uT: {advice}"
    limit_pct = t.max_circle_residual_pct if q.get("geometry") == Geometry.CIRCLE.value else t.max_residual_pct
    if pct is not None and pct > factor * limit_pct:
        return f"{name} {pct:.1f} % > {factor * limit_pct:.1f} %: {advice}"
    return None


def _check_radius(q: Mapping[str, Any], t: GateThresholds) -> str | None:
    ratio = _num(q, "radius_ratio")
    if ratio is None or abs(ratio - 1.0) * 100.0 <= t.radius_tolerance_pct:
        return None
    return (f"fitted radius {q.get('radius', 0):.1f} uT is {100 * (ratio - 1):+.0f} % off the expected "
            f"{q.get('expected_field_ut', 0):.1f} uT (limit +-{t.radius_tolerance_pct:g} %): check the location, "
            "the unit of the data, and for nearby iron")


def _check_soft_iron(q: Mapping[str, Any], t: GateThresholds) -> str | None:
    value = _num(q, "soft_iron_condition")
    if value is None or value <= t.max_soft_iron_condition:
        return None
    return (f"soft-iron axis ratio {value:.2f} > {t.max_soft_iron_condition:g}: the sensor sits too close to "
            "iron or a magnet, or the samples cover too little; move it and calibrate again")


def _check_dip(q: Mapping[str, Any], t: GateThresholds) -> str | None:
    value = _num(q, "dip_spread_deg")
    if value is None or value <= t.max_dip_spread_deg:
        return None
    advice = ("keep away from iron and other devices" if q.get("dip_source") == "fused gravity" else
              "hold still while sampling (the accelerometer must see gravity only) and keep away from iron")
    return f"dip-angle spread {value:.1f} deg > {t.max_dip_spread_deg:g} deg: {advice}"


#: the checks in the order their reasons are reported (the most fundamental first)
_CHECKS = (_check_scatter, _check_coverage, _check_residual, _check_holdout, _check_radius, _check_soft_iron,
           _check_dip, check_consistency)


def gate(quality: Mapping[str, Any], thresholds: GateThresholds | None = None) -> tuple[bool, str]:
    """(accepted, reason): reason lists every failed check, most fundamental first, each with what to do."""
    thresholds = thresholds or GateThresholds()
    failures = [reason for check in _CHECKS if (reason := check(quality, thresholds))]
    if failures:
        return False, "; ".join(failures)
    return True, _summary(quality)


def _summary(q: Mapping[str, Any]) -> str:
    ut, pct = _num(q, "residual_rms_ut"), _num(q, "residual_rms_pct")
    residual = f"residual {ut:.2f} uT ({pct:.2f} %)" if ut is not None else f"residual {pct:.2f} %"
    if q.get("geometry") == Geometry.TURNTABLE.value:
        return f"accepted: {residual}"
    return f"accepted: {residual}, coverage {100 * float(q.get('coverage', 0)):.0f} %"
