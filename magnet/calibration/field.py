"""Calibration in the field: the model the motion identifies (``magnet.calibration.ladder``), judged by what it does
to heading (docs/field-calibration.md).

``fit_field`` is what ``auto`` falls back to when the sphere's methods are refused, and what ``--method offset``,
``offset+scale`` and ``planar`` ask for directly. The record:

- ``method``: the rung fitted ("offset", "offset+scale", "planar" or "ellipsoid");
- quality ``model`` (the rung), ``estimated`` and ``kept`` (parameters, in words), ``kept_from`` (the calibration in
  force, or the identity), ``identified_deg`` (each rung tried: the heading error its parameters' noise leaves, deg)
  and ``information_eigenvalues`` (the chosen rung's), ``why`` (one sentence), ``planar`` ("planar: within 20 deg of
  level") for a device kept level; ``vertical_kept`` when a level device with no place (neither |B| nor dip) kept the
  calibration in force's vertical offset (with nothing in force it is refused: ``magnet.calibration.unplaced``);
- judged (``judge``): the held-out heading consistency (``magnet.quality.motion``: every 5th block of 20 samples is
  left out of a second fit of the same rung and scored) must beat the calibration in force (or none) by its margin;
  the residual, held-out residual, radius against the WMM and the soft-iron condition are checked as for any fit.
  Coverage and the scatter of the raw cloud are not asked of these rungs: identifiability stands in for them.
"""

from __future__ import annotations

import contextlib
import dataclasses
import math
from typing import Any

import numpy as np

from magnet import frames
from magnet.calibration import base, candidates, course, disturbed, turning, unplaced
from magnet.calibration.base import FitError
from magnet.calibration.field_input import MIN_FIELD_SAMPLES
from magnet.calibration.field_input import FieldInput as FieldInput  # the record, named where the fit is
from magnet.calibration.ladder import AUTO_HINT, IDENTIFIED_DEG, RungFit, first_offset, fit_rung
from magnet.calibration.level import level_in_turns
from magnet.calibration.rungs import (
    LEVEL_OFFSET,
    OFFSET,
    PLANAR,
    PLANAR_NOTE,
    RUNGS,
    SCALE,
    Evidence,
    Rung,
    gyro_spans,
    is_planar,
)
from magnet.model import Calibration
from magnet.quality import GateThresholds, Geometry, assess, chance, for_travel, gate, motion, ut_per_unit
from magnet.quality.stats import take_rows
from magnet.quality.units_hint import earth_range_refusal

#: a field record must make the held-out consistency better than the reference's by this fraction of it too (beside
#: the comparison's statistical margin): the consistency is judged with the gyroscope filter's own attitude, whose
#: errors weigh on both sides, so a gain of a few % is not a gain in heading (BROAD trial 01, factory-calibrated: a
#: field ellipsoid 4 % more consistent made causal heading 17 % worse)
MIN_GAIN = 0.15
#: what a record from the velocity's heading says in its quality ``heading_source``
COURSE_SOURCE = course.COURSE_SOURCE
#: held-out blocks: as ``magnet.calibration.fitting`` (``base.holdout_mask``: blocks of HOLDOUT_BLOCK_S seconds)
HOLDOUT_BLOCK, HOLDOUT_EVERY = base.HOLDOUT_BLOCK, base.HOLDOUT_EVERY


def _work_scale(unit: str) -> float:
    """Raw unit -> the working unit (uT where the unit converts, else the raw unit)."""
    return ut_per_unit(unit) or 1.0


def _kept(inp: FieldInput, scale: float) -> tuple[np.ndarray, np.ndarray, str]:
    """(A0 in the working unit, kept offset in it, where A0 comes from)."""
    ref = inp.reference
    usable = ref is not None and ref.unit == inp.unit and ref.method not in ("identity",)
    if not usable or ref is None:
        return np.eye(3), np.zeros(3), "identity"
    matrix = np.asarray(ref.matrix, dtype=float) / scale
    matrix = matrix / np.cbrt(abs(np.linalg.det(matrix)))  # its shape; the scale follows from F
    return matrix, np.asarray(ref.offset, dtype=float) * scale, "the calibration in force"


def _evidence(
    inp: FieldInput, ev_motion: motion.MotionEvidence | None, rows: np.ndarray | None = None
) -> tuple[Evidence, str]:
    scale = _work_scale(inp.unit)
    mag = inp.mag * scale
    matrix0, offset0, source = _kept(inp, scale)
    down = None if ev_motion is None else ev_motion.down
    spans = None
    if inp.gyr is not None and inp.period_s is not None:
        spans = gyro_spans(np.asarray(inp.gyr, dtype=float), inp.period_s, rows)
    field = inp.field_ut if inp.field_ut is not None and ut_per_unit(inp.unit) else None
    if field is None:  # the cloud's own radius
        centre = first_offset(Evidence(mag, None, spans, inp.period_s, 1.0, None, matrix0, offset0))
        field = float(np.median(np.linalg.norm((mag - centre) @ matrix0.T, axis=1)))
    vertical = None if inp.dip_deg is None else field * math.sin(math.radians(inp.dip_deg))
    return Evidence(mag, down, spans, inp.period_s, field, vertical, matrix0, offset0), source


def _record(result: RungFit, inp: FieldInput, ev: Evidence, count: int) -> Calibration:
    """The rung's solution as a record in the raw unit (output uT where known; scaled to field_ut otherwise)."""
    scale = _work_scale(inp.unit)
    to_ut = ut_per_unit(inp.unit)
    matrix = result.matrix * scale
    output_unit = "ut" if to_ut else inp.unit
    if not to_ut and inp.field_ut is not None:
        matrix, output_unit = matrix * inp.field_ut / ev.field_ut, "ut"
    strength = inp.field_ut if inp.field_ut is not None else ev.field_ut * (to_ut or 1.0) / scale
    return Calibration(
        method=result.rung.name,
        offset=result.offset / scale,
        matrix=matrix,
        field_strength=float(strength),
        sample_count=count,
        unit=inp.unit,
        output_unit=output_unit,
    )


def _holdout_mask(inp: FieldInput) -> np.ndarray:
    """The input's held-out rows (``base.holdout_mask``: blocks of HOLDOUT_BLOCK_S seconds of its samples)."""
    return base.holdout_mask(len(inp.mag), inp.period_s)


def fit_field(
    inp: FieldInput, *, rung: str | None = None, gate_thresholds: GateThresholds | None = None
) -> Calibration:
    """The field fit of ``inp`` (the rung the motion identifies, or ``rung`` by name), with quality and the
    judgement (module docstring). Raises FitError when no rung can be computed or none is identified."""
    ev_motion = _motion_evidence(inp)
    whole_input, keep = inp, disturbed.kept_rows(inp.disturbed)
    ev, source = _evidence(inp, ev_motion, keep)
    if keep is not None:  # the undisturbed samples alone, the gyroscope's windows between them kept
        inp, ev, ev_motion = disturbed.undisturbed(inp, ev, ev_motion, keep, MIN_FIELD_SAMPLES)
    planar = is_planar(ev.down)  # a level vehicle's turns may vouch for its first record (``chance.vehicle``):
    test, vehicle = _holdout_mask(inp), planar and keep is None and chance.vehicle(inp.acc, inp.period_s)
    windows, whole_mag = turning.vehicle_turns(whole_input, planar, keep), whole_input.mag
    field_known = inp.field_ut is not None and bool(ut_per_unit(inp.unit))
    ev, vertical_kept = unplaced.hold_vertical(ev, source, planar, field_known)  # no place: what holds it
    if planar and (ev_motion is None or ev_motion.source != motion.AIDED_SOURCE):
        ev = level_in_turns(ev, inp.gyr, inp.vel_ned_ms)

    def judged(result: RungFit, tried: dict[str, float]) -> Calibration:
        made, holdout = _record(result, inp, ev, len(inp.mag)), _holdout(inp, ev, result, test)
        record = judge(inp, made, result, tried, source, planar, ev_motion, test, holdout, gate_thresholds, vehicle)
        record = turning.with_turn_residual(unplaced.with_vertical_kept(record, vertical_kept), windows, whole_mag)
        if not result.unidentified and inp.field_ut is not None:  # a refresh's turns, where the rule identified it
            record = turning.judged_by_turns(record, windows, whole_mag, _usable(inp.reference, inp), gate_thresholds)
        if keep is None:
            return record
        return record.replace(quality=record.quality.with_extra(disturbed_samples=int((~keep).sum())))

    if rung is not None:
        result = _forced_fit(ev, rung, planar)
        return judged(result, {result.rung.name: result.identified_deg})
    try:
        found, tried = candidates.identified(ev, planar)
    except FitError as refused:
        fallback = _course_fit(whole_input, ev, source, gate_thresholds)
        if fallback is None:
            raise
        return fallback.replace(reason=f"{fallback.reason}; the magnetometer and gyroscope alone: {refused}")
    with contextlib.suppress(FitError, np.linalg.LinAlgError):  # no sphere: the rungs alone
        if not planar or ev.vertical_ut is not None:  # its radius free, only the dip moves its vertical centre
            found.append(candidates.sphere_fit(ev))
    chosen = candidates.best([(result, judged(result, tried)) for result in found])
    if chosen.accepted:
        return chosen
    # the velocity's heading may tell what they could not
    fallback = _course_fit(whole_input, ev, source, gate_thresholds)
    if fallback is None or not fallback.accepted:
        return chosen
    return fallback.replace(reason=f"{fallback.reason}; the magnetometer and gyroscope alone: {chosen.reason}")


#: why a planar device's ``offset+scale`` is refused (the ladder does not fit it there)
LEVEL_GAIN = (
    "the gain along the device's mean vertical and the offset along it: turns about a vertical held near one attitude "
    "cannot tell them apart (the ladder fits planar there, which keeps that gain); fit --method planar or offset, or "
    "tilt the device (roll and pitch by 30 deg or more while turning)"
)


def forced_rung(name: str, planar: bool) -> Rung:
    """The rung ``--method NAME`` fits: as the ladder fits it, so a planar device's ``offset`` keeps the matrix whole
    (``LEVEL_OFFSET``: a level device cannot tell its gain from its vertical offset, which the WMM's dip then holds)."""
    named = RUNGS[name]
    return LEVEL_OFFSET if planar and named is OFFSET else named


def _forced_fit(ev: Evidence, name: str, planar: bool) -> RungFit:
    """The rung ``--method NAME`` asks for (``forced_rung``), fitted; ``unidentified`` set when the ladder's rule
    does not identify it (a planar device's offset+scale: ``LEVEL_GAIN``)."""
    named = forced_rung(name, planar)
    result = fit_rung(ev, named, first_offset(ev))
    if result.unidentified:
        return dataclasses.replace(result, unidentified=result.unidentified + AUTO_HINT)
    if planar and named is SCALE:
        return dataclasses.replace(result, unidentified=LEVEL_GAIN)
    return result


def _motion_evidence(inp: FieldInput) -> motion.MotionEvidence | None:
    """The tilt the fit and its judgement see: velocity aided where it can be (``_aided_evidence``: a vehicle's
    accelerations do not bend it), else from the gyroscope and accelerometer; None without an accelerometer."""
    aided = _aided_evidence(inp)
    if aided is not None or inp.acc is None:
        return aided
    try:
        return motion.evidence(np.asarray(inp.acc, dtype=float), inp.gyr, inp.period_s)
    except ValueError as exc:
        raise FitError(str(exc)) from None


def _course_fit(inp: FieldInput, ev: Evidence, source: str, thresholds: GateThresholds | None) -> Calibration | None:
    """The offset from the velocity over the ground (``magnet.calibration.course.fit_course``) for a planar device
    whose samples carry a velocity and whose place is known, in uT units; None when it does not apply."""
    known = (inp.vel_ned_ms, inp.gyr, inp.acc, inp.period_s, inp.field_ut, inp.dip_deg, inp.declination_deg)
    if any(value is None for value in known) or not is_planar(ev.down) or inp.unit != "ut":
        return None
    assert inp.gyr is not None and inp.acc is not None and inp.period_s is not None and inp.vel_ned_ms is not None
    assert inp.field_ut is not None and inp.dip_deg is not None and inp.declination_deg is not None
    place = course.Place(inp.field_ut, inp.dip_deg, inp.declination_deg)
    chosen = for_travel(thresholds)
    keep = disturbed.kept_rows(inp.disturbed)  # a disturbed field enters this fit neither
    motion_in = course.Motion(inp.mag, inp.acc, inp.gyr, inp.period_s, inp.vel_ned_ms, keep)
    record = course.fit_course(motion_in, place, ev.matrix0, _usable(inp.reference, inp), source, chosen, MIN_GAIN)
    if record is None or keep is None:
        return record
    return record.replace(quality=record.quality.with_extra(disturbed_samples=int((~keep).sum())))


def _usable(reference: Calibration | None, inp: FieldInput) -> Calibration | None:
    """The calibration in force when it corrects this input's unit to uT (its heading can aid), else None."""
    ok = reference is not None and reference.unit == inp.unit and reference.method != "identity"
    return reference if ok and reference is not None and reference.output_unit == "ut" else None


def _aided_evidence(inp: FieldInput) -> motion.MotionEvidence | None:
    """The velocity-aided motion evidence (``magnet.quality.motion.Aiding``) when the samples carry a velocity (with
    a gyroscope and an accelerometer) and a calibration is in force, whose heading turns the velocity's acceleration
    into the body frame; None otherwise.

    Without a calibration in force the evidence stays unaided: the first fit's heading could aid it too, but with
    the vehicle's accelerations gone the raw field's departures from a constant field are left in the turns alone,
    and the held-out comparison with no calibration (its margin from the spread over ten runs of samples) then calls
    a ten-fold gain chance (car, whole run: 0.80 deg against 8.56, margin 8.56)."""
    reference = _usable(inp.reference, inp)
    if inp.vel_ned_ms is None or inp.gyr is None or inp.acc is None or inp.period_s is None or reference is None:
        return None
    vel = np.asarray(inp.vel_ned_ms, dtype=float)
    if not np.isfinite(vel).all(axis=1).any():
        return None
    t_s = np.arange(len(inp.mag)) * inp.period_s
    magnetic = frames.to_magnetic_ned(vel, inp.declination_deg or 0.0)
    aiding = motion.Aiding(t_s, magnetic, reference.apply(inp.mag))
    try:
        return motion.evidence(np.asarray(inp.acc, dtype=float), inp.gyr, inp.period_s, aiding)
    except ValueError as exc:
        raise FitError(str(exc)) from None


def _kept_spans(
    spans: tuple[np.ndarray, np.ndarray, np.ndarray], keep: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    ok = keep[spans[0]] & keep[spans[1]]
    return spans[0][ok], spans[1][ok], spans[2][ok]


def _holdout(
    inp: FieldInput, whole: Evidence, result: RungFit, test: np.ndarray
) -> tuple[np.ndarray, Calibration] | None:
    """(held-out raw samples, the same rung fitted without them), None when that fit fails."""
    train = ~test
    ev = whole if whole.spans is None else dataclasses.replace(whole, spans=_kept_spans(whole.spans, train))
    try:
        trained = candidates.refit(ev, result, train)
    except (FitError, np.linalg.LinAlgError):
        return None
    return take_rows(inp.mag, test), _record(trained, inp, ev, int(train.sum()))


def _why(result: RungFit, tried: dict[str, float], planar: bool) -> str:
    if result.rung is candidates.SPHERE:
        text = (
            "offset: a plain sphere fit, its radius free (where the motion leaves the vertical offset unknown, the "
            "scale takes it, which heading at this attitude does not see)"
        )
        return f"{text}; {PLANAR_NOTE}" if planar else text
    others = {name: value for name, value in tried.items() if name != result.rung.name}
    richer = [f"{name} {value:.2g} deg" for name, value in others.items() if not value <= IDENTIFIED_DEG]
    also = [f"{name} {value:.2g} deg" for name, value in others.items() if value <= IDENTIFIED_DEG]
    if result.unidentified:  # a rung asked for by name that the motion does not identify
        text = (
            f"{result.rung.name} (heading error from its noise {result.identified_deg:.2g} deg, limit "
            f"{IDENTIFIED_DEG:g}): the motion does not identify {result.unidentified}"
        )
        return f"{text}; {PLANAR_NOTE}" if planar else text
    text = (
        f"{result.rung.name}: the motion identifies {', '.join(result.rung.estimated)} (heading error from its noise "
        f"{result.identified_deg:.2g} deg <= {IDENTIFIED_DEG:g})"
    )
    if richer:
        text += f"; not identified: {', '.join(richer)}"
    if also:  # identified too, and judged less good by held-out heading
        text += f"; also identified: {', '.join(also)}"
    if planar:
        text += f"; {PLANAR_NOTE}"
    return text


def judge(
    inp: FieldInput,
    calibration: Calibration,
    result: RungFit,
    tried: dict[str, float],
    source: str,
    planar: bool,
    ev_motion: motion.MotionEvidence | None,
    test: np.ndarray,
    holdout: tuple[np.ndarray, Calibration] | None,
    thresholds: GateThresholds | None = None,
    level_turns: bool = False,
) -> Calibration:
    """The record with its quality and verdict: the figures of ``assess`` and of ``magnet.quality.motion`` (against
    the calibration in force, else none), gated with coverage and scatter left out (identifiability stands in).
    level_turns: the comparison with no calibration may stand on the device's turns (``magnet.quality.chance``)."""
    to_ut = ut_per_unit(inp.unit)
    corrected = calibration.apply(inp.mag)
    quality = assess(
        inp.mag,
        calibration,
        corrected=corrected,
        geometry=Geometry.SPHERE,
        expected_field_ut=inp.field_ut,
        fitted_radius_ut=None,
        holdout=holdout,
    )
    if ev_motion is not None:
        quality = motion.with_motion_figures(
            quality, inp.mag, calibration, ev_motion, test, holdout, inp.reference, corrected, level_turns
        )
    extra: dict[str, Any] = {
        "model": result.rung.name,
        "estimated": list(result.rung.estimated),
        "kept": list(result.rung.kept),
        "kept_from": source,
        "identified_deg": {name: _finite(value) for name, value in tried.items()},
        "information_eigenvalues": [_finite(v) for v in result.eigenvalues],
        "block_spread_ut": dict(result.sigma_ut),
        "vertical_ut": result.vertical_ut,
        "why": _why(result, tried, planar),
    }
    if planar or result.rung is PLANAR:
        extra["planar"] = PLANAR_NOTE
    quality = quality.with_extra(**extra)
    chosen = for_travel(thresholds)
    accepted, reason = gate(quality, chosen)
    small = _small_gain(quality)
    if accepted and small:
        accepted, reason = False, small
    if result.unidentified:  # the identifiability rule, for a rung asked for by name as for the ladder's
        unknown = f"refused by the identifiability rule ({result.rung.name} asked for)"
        accepted, reason = False, unknown if accepted or small else f"{unknown}; {reason}"
    if inp.field_ut is None and calibration.output_unit == "ut" and to_ut is not None:
        earth = earth_range_refusal(float(np.median(np.linalg.norm(corrected, axis=1))) / to_ut, to_ut)
        accepted, reason = (False, earth if accepted else f"{earth}; {reason}") if earth else (accepted, reason)
    if to_ut is None and inp.field_ut is None:
        reason = f"{reason}; radius not checked (raw counts and no expected field)"
    return calibration.replace(quality=quality, accepted=accepted, reason=f"{reason}; {extra['why']}")


def _small_gain(quality: Any) -> str | None:
    """The refusal when the held-out consistency gains less than MIN_GAIN of the reference's (None: enough, or
    not measured)."""
    held, ref = quality.get("holdout_consistency_deg"), quality.get("reference_holdout_consistency_deg")
    if held is None or ref is None or held <= (1.0 - MIN_GAIN) * ref:
        return None
    return (
        f"the fit makes the field only {100 * (1 - held / ref):.0f} % more constant than "
        f"{quality.get('reference') or 'no calibration'} on held-out data ({held:.2f} deg vs {ref:.2f} deg; a field "
        f"fit must gain {100 * MIN_GAIN:.0f} %): the calibration in force is good enough"
    )


def _finite(value: float) -> float | None:
    return float(value) if math.isfinite(value) else None
