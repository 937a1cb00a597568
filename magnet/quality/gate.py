"""The gate that accepts or refuses a calibration on its figures of merit, each refusal with what to do."""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping
from typing import Any

from magnet.model import Quality
from magnet.quality.figures import Geometry
from magnet.quality.motion import check_consistency

#: the figures, as a ``Quality`` or its map
QualityLike = Quality | Mapping[str, Any]


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


#: a field fit's |B| residual limits are this many times a tumble's: its samples come from a path through space, where
#: the local field itself varies (BROAD's motion-capture lab, a factory-calibrated sensor tumbled in one spot: 1.66-1.77
#: uT against the 1.6 uT limit; a walk crosses the room), and its rung's heading figure already carries the residual's
#: spread (docs/field-calibration.md, "The field's own variation along a path")
TRAVEL_RESIDUAL_FACTOR = 2.0


def for_travel(thresholds: GateThresholds | None = None) -> GateThresholds:
    """The gate of a fit from motion through space (the field ladder's rungs, a vehicle's course fit and its refresh
    judged by turns): no coverage or scatter asked (identifiability stands in for them), the residual limits
    ``TRAVEL_RESIDUAL_FACTOR`` times ``thresholds``' (default ``GateThresholds()``)."""
    base = thresholds or GateThresholds()
    return dataclasses.replace(
        base,
        min_coverage=0.0,
        max_scatter_condition=math.inf,
        max_residual_ut=TRAVEL_RESIDUAL_FACTOR * base.max_residual_ut,
        max_residual_pct=TRAVEL_RESIDUAL_FACTOR * base.max_residual_pct,
    )


def _num(quality: QualityLike, key: str) -> float | None:
    value = quality.get(key)
    return None if value is None else float(value)


def _check_scatter(q: QualityLike, t: GateThresholds) -> str | None:
    value = _num(q, "scatter_condition")
    if value is None or value <= t.max_scatter_condition:
        return None
    if q.get("geometry") == Geometry.CIRCLE.value:
        return f"samples lie on a line (scatter condition {value:.3g}): turn the device through a full circle"
    return (
        f"samples are coplanar (scatter condition {value:.3g} > {t.max_scatter_condition:g}): a level turn cannot "
        "give a 3D fit; tumble the device through all attitudes, or use minmax2d for level use"
    )


def _check_coverage(q: QualityLike, t: GateThresholds) -> str | None:
    geometry = q.get("geometry", Geometry.SPHERE.value)
    limit = {Geometry.SPHERE.value: t.min_coverage, Geometry.CIRCLE.value: t.min_heading_coverage}.get(geometry)
    value = _num(q, "coverage")
    if limit is None or value is None or value >= limit:
        return None
    advice = ", ".join(q.get("missing_directions") or ()) or "move through more attitudes"
    return f"coverage {100 * value:.0f} % < {100 * limit:.0f} %: {advice}"


def _check_residual(q: QualityLike, t: GateThresholds) -> str | None:
    return _residual_reason(q, t, "residual_rms", 1.0, "residual")


def _check_holdout(q: QualityLike, t: GateThresholds) -> str | None:
    return _residual_reason(q, t, "holdout_rms", t.max_holdout_factor, "held-out residual")


#: what to do about a large residual, by geometry
_RESIDUAL_ADVICE: dict[str, str] = {
    Geometry.SPHERE.value: "keep magnets and metal away, move slowly, and check the sensor is not saturating",
    Geometry.CIRCLE.value: (
        "the turn is not a circle after min/max scaling (a tilted ellipse from cross-axis soft "
        "iron, or the device tilted while turning): keep it level, or tumble it and use ellipsoid"
    ),
    Geometry.TURNTABLE.value: (
        "the readings do not fit one linear model: check the mountings, the table angles and the field components"
    ),
}


def _residual_reason(q: QualityLike, t: GateThresholds, prefix: str, factor: float, name: str) -> str | None:
    ut, pct = _num(q, f"{prefix}_ut"), _num(q, f"{prefix}_pct")
    advice = _RESIDUAL_ADVICE.get(q.get("geometry", Geometry.SPHERE.value), _RESIDUAL_ADVICE["sphere"])
    if ut is not None and ut > factor * t.max_residual_ut:
        return f"{name} {ut:.2f} uT > {factor * t.max_residual_ut:.2f} uT: {advice}"
    limit_pct = t.max_circle_residual_pct if q.get("geometry") == Geometry.CIRCLE.value else t.max_residual_pct
    if pct is not None and pct > factor * limit_pct:
        return f"{name} {pct:.1f} % > {factor * limit_pct:.1f} %: {advice}"
    return None


def _check_radius(q: QualityLike, t: GateThresholds) -> str | None:
    ratio = _num(q, "radius_ratio")
    if ratio is None or abs(ratio - 1.0) * 100.0 <= t.radius_tolerance_pct:
        return None
    return (
        f"fitted radius {q.get('radius', 0):.1f} uT is {100 * (ratio - 1):+.0f} % off the expected "
        f"{q.get('expected_field_ut', 0):.1f} uT (limit +-{t.radius_tolerance_pct:g} %): check the location, "
        "the unit of the data, and for nearby iron"
    )


def _check_soft_iron(q: QualityLike, t: GateThresholds) -> str | None:
    value = _num(q, "soft_iron_condition")
    if value is None or value <= t.max_soft_iron_condition:
        return None
    return (
        f"soft-iron axis ratio {value:.2f} > {t.max_soft_iron_condition:g}: the sensor sits too close to "
        "iron or a magnet, or the samples cover too little; move it and calibrate again"
    )


def _check_dip(q: QualityLike, t: GateThresholds) -> str | None:
    value = _num(q, "dip_spread_deg")
    if value is None or value <= t.max_dip_spread_deg:
        return None
    advice = (
        "keep away from iron and other devices"
        if q.get("dip_source") == "fused gravity"
        else "hold still while sampling (the accelerometer must see gravity only) and keep away from iron"
    )
    return f"dip-angle spread {value:.1f} deg > {t.max_dip_spread_deg:g} deg: {advice}"


#: the checks in the order their reasons are reported (the most fundamental first)
_CHECKS = (
    _check_scatter,
    _check_coverage,
    _check_residual,
    _check_holdout,
    _check_radius,
    _check_soft_iron,
    _check_dip,
    check_consistency,
)


def gate(quality: QualityLike, thresholds: GateThresholds | None = None) -> tuple[bool, str]:
    """(accepted, reason): reason lists every failed check, most fundamental first, each with what to do."""
    thresholds = thresholds or GateThresholds()
    failures = [reason for check in _CHECKS if (reason := check(quality, thresholds))]
    if failures:
        return False, "; ".join(failures)
    return True, _summary(quality)


def _summary(q: QualityLike) -> str:
    ut, pct = _num(q, "residual_rms_ut"), _num(q, "residual_rms_pct")
    residual = f"residual {ut:.2f} uT ({pct:.2f} %)" if ut is not None else f"residual {pct:.2f} %"
    if q.get("geometry") == Geometry.TURNTABLE.value:
        return f"accepted: {residual}"
    return f"accepted: {residual}, coverage {100 * float(q.get('coverage', 0)):.0f} %"
