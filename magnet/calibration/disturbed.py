"""Which samples a fit leaves out because the field was disturbed (a steel door, a parked car, a magnet passed on the
way): the rule is ``magnet.quality.disturbance.disturbed_samples`` (the same steps and |B| tolerance as the compass's
watch, ``magnet.attitude.field_watch``), judged here for one ``FitInput`` (docs/field-calibration.md, "Disturbed
samples").

- with a calibration in force (``FitInput.reference``, correcting to uT): the corrected field's |B| and dip against
  the World Magnetic Model's at the place, and its steps in the frame the gyroscope holds still;
- without one: the raw field's steps beyond what the gyroscope's turns can make (``raw_steps``); then, in ``auto``,
  once more with the first fit's correction (``refine``), and the fit is made again when that finds more;
- when that fit is refused (or cannot be made) and no calibration is in force: the doors judged with a plain sphere
  through the samples kept so far (``sphere_judged``), the sphere fitted again without what it finds, up to
  SPHERE_ROUNDS times, and the fit made once more on what is left. A hard iron many times the field hides a door's
  step within the raw field's turns (in a pocket, raw steps found 9 % of a walk's door samples over 3 uT), so the
  first fit takes them, and its refusal leaves nothing to judge them with; a sphere, bent by them at first, finds
  the strongest, and refitted without them finds the rest (fieldsim's pocket walk past doors, seed 2027: the
  sphere's centre 59 -> 30 -> 8 uT from the truth, 9 -> 37 -> 90 % of those samples found).

A correction under which more than MAX_SHARE of the samples look disturbed is the one in question, not the field:
the raw steps are used instead; raw steps over more than MAX_SHARE of the samples (a gyroscope that does not turn
with the magnetometer) drop nothing. Pure numpy.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from typing import TYPE_CHECKING

import numpy as np

from magnet.calibration.base import FitError
from magnet.calibration.fit_input import FitInput
from magnet.earth.geomag import earth_field
from magnet.model import Calibration
from magnet.quality.disturbance import disturbed_samples
from magnet.units import ut_per_unit

if TYPE_CHECKING:
    from magnet.calibration.field_input import FieldInput
    from magnet.calibration.rungs import Evidence
    from magnet.quality.motion import MotionEvidence

#: a correction that finds more than this share of the samples disturbed is not trusted to judge them
MAX_SHARE = 0.5
#: ``refine`` fits again when the first fit's correction finds at least this share of the samples more
REFIT_SHARE = 0.01
#: the rounds of a provisional sphere's judgement when a fit is refused (``sphere_judged``)
SPHERE_ROUNDS = 3


def _expected(data: FitInput) -> tuple[float | None, float | None]:
    """(|B| uT, dip deg) expected at the input's place: the given ones, else the WMM's, else None."""
    field_ut, dip = data.field_ut, data.dip_deg
    if (field_ut is None or dip is None) and data.place is not None:
        earth = earth_field(*data.place.as_tuple(), data.date)
        field_ut = earth.total_ut if field_ut is None else field_ut
        dip = earth.inclination_deg if dip is None else dip
    return field_ut, dip


def _usable(correction: Calibration | None, data: FitInput) -> Calibration | None:
    ok = correction is not None and correction.unit == data.unit and correction.output_unit == "ut"
    return correction if ok and correction is not None and correction.method != "identity" else None


def mask(data: FitInput, correction: Calibration | None = None) -> np.ndarray:
    """(N,) bool: the input's disturbed samples, judged with ``correction`` (None: the calibration in force, if it
    corrects to uT), else from the raw field."""
    field_ut, dip = _expected(data)
    gyr, period = (data.gyr_rads, data.period_s) if data.has_gyroscope else (None, None)
    mag = np.asarray(data.mag, dtype=float)
    chosen = _usable(correction if correction is not None else data.reference, data)

    def flags(correction: Calibration | None) -> np.ndarray:
        return disturbed_samples(
            mag,
            data.unit,
            acc=data.acc,
            gyr_rads=gyr,
            period_s=period,
            correction=correction,
            expected_ut=field_ut,
            expected_dip_deg=dip,
        )

    raw = flags(None)
    if raw.mean() > MAX_SHARE:  # the gyroscope does not explain the field: the rule, not the field, is in question
        raw = np.zeros(len(mag), dtype=bool)
    if chosen is None:
        return raw
    judged = flags(chosen)
    return raw if judged.mean() > MAX_SHARE else judged | raw


def judged(data: FitInput) -> FitInput:
    """The input with ``disturbed`` set (``mask``), unless it is already or ``drop_disturbed`` is off."""
    if data.disturbed is not None or not data.drop_disturbed or len(data.mag) == 0:
        return data
    try:
        return data.replace(disturbed=mask(data))
    except ValueError:  # arrays the fit will refuse with its own message
        return data


def kept(data: FitInput) -> np.ndarray | None:
    """(N,) bool: the rows a fit takes, None when it takes them all."""
    if not data.drop_disturbed or data.disturbed is None:
        return None
    flags = np.asarray(data.disturbed, dtype=bool)
    if flags.shape != (len(data.mag),):
        raise ValueError(f"disturbed must be one flag per sample ({len(data.mag)},), got {flags.shape}")
    return kept_rows(flags)


def refined(data: FitInput, first: Calibration) -> FitInput | None:
    """The input with the samples ``first`` (a fit of it, made without a calibration in force) finds disturbed
    added, when that adds at least REFIT_SHARE of them; None otherwise (nothing to fit again)."""
    if not data.drop_disturbed or data.reference is not None or _usable(first, data) is None:
        return None
    before = np.zeros(len(data.mag), dtype=bool) if data.disturbed is None else np.asarray(data.disturbed, bool)
    again = mask(data, first) | before
    if (again & ~before).sum() < REFIT_SHARE * len(again):
        return None
    return data.replace(disturbed=again)


def sphere_correction(data: FitInput, rows: np.ndarray) -> Calibration | None:
    """A plain sphere |m - c| = r through the rows (N,) bool of the raw samples, by algebraic least squares, as a
    correction to uT (the matrix the identity times F / r, F the expected |B|, else r in uT): a provisional
    correction to judge disturbed samples with, never a record. None when the rows give no sphere or the unit does
    not convert to uT and no |B| is expected."""
    field_ut, _ = _expected(data)
    mag = np.asarray(data.mag, dtype=float)[rows]
    if len(mag) < 10 or not np.all(np.isfinite(mag)):
        return None
    design = np.column_stack([2.0 * mag, np.ones(len(mag))])
    solution, *_ = np.linalg.lstsq(design, np.sum(mag * mag, axis=1), rcond=None)
    centre = solution[:3]
    squared = float(solution[3] + centre @ centre)
    to_ut = ut_per_unit(data.unit)
    if not np.isfinite(squared) or squared <= 0 or (field_ut is None and to_ut is None):
        return None
    radius = np.sqrt(squared)
    scale = float(field_ut) / radius if field_ut else float(to_ut)  # type: ignore[arg-type]
    return Calibration(
        method="sphere", offset=centre, matrix=np.eye(3) * scale, field_strength=radius * scale, unit=data.unit
    )


def sphere_judged(data: FitInput) -> FitInput | None:
    """The input (its ``disturbed`` set by ``judged``, no calibration in force) with the samples a provisional sphere
    finds disturbed added: the sphere through the samples kept so far judges every sample (``mask``), then is fitted
    again without what it found, up to SPHERE_ROUNDS times, until it finds nothing new (or more than MAX_SHARE: it
    is in question then, and what it found last is kept). None when it adds fewer than REFIT_SHARE of the samples,
    or there is nothing to judge with (no gyroscope: the steps need the time order)."""
    if not data.drop_disturbed or data.reference is not None or not data.has_gyroscope or len(data.mag) == 0:
        return None
    before = np.zeros(len(data.mag), dtype=bool) if data.disturbed is None else np.asarray(data.disturbed, bool)
    flags = before
    for _ in range(SPHERE_ROUNDS):
        sphere = sphere_correction(data, ~flags)
        if sphere is None:
            break
        found = mask(data, sphere)
        if found.mean() > MAX_SHARE or not (found & ~flags).any():
            break
        flags = found | before
    if (flags & ~before).sum() < REFIT_SHARE * len(flags):
        return None
    return data.replace(disturbed=flags)


def fit_undisturbed(data: FitInput, fit_once: Callable[[FitInput], Calibration]) -> Calibration:
    """``fit_once`` on ``data`` with its disturbed samples left out (``judged``), then once more when its result
    finds more of them (``refined``); the first result when too few samples are left for the second. When that is
    refused (or raises FitError) without a calibration in force, once more with what a provisional sphere finds
    disturbed (``sphere_judged``): its result when accepted, else the refusal as it was."""
    data = judged(data)
    try:
        result: Calibration | FitError = _fit_refined(data, fit_once)
    except FitError as exc:
        result = exc
    if isinstance(result, Calibration) and result.accepted:
        return result
    again = sphere_judged(data)
    if again is not None:
        try:
            retried = _fit_refined(again, fit_once)
            if retried.accepted:
                return retried
        except FitError:
            pass
    if isinstance(result, FitError):
        raise result
    return result


def _fit_refined(data: FitInput, fit_once: Callable[[FitInput], Calibration]) -> Calibration:
    """``fit_once`` on ``data``, then once more when its result finds more disturbed samples (``refined``)."""
    first = fit_once(data)
    again = refined(data, first)
    if again is None:
        return first
    try:
        return fit_once(again)
    except FitError:  # too few samples left: the first
        return first


def kept_rows(flags: np.ndarray | None) -> np.ndarray | None:
    """(N,) bool: the rows not flagged (N,), None when none is."""
    return None if flags is None or not np.any(flags) else ~np.asarray(flags, dtype=bool)


def undisturbed(
    inp: FieldInput, ev: Evidence, ev_motion: MotionEvidence | None, keep: np.ndarray, fewest: int
) -> tuple[FieldInput, Evidence, MotionEvidence | None]:
    """A field fit's input, evidence and motion evidence on the kept rows (N,) bool only (the gyroscope's windows
    whose two ends are kept stay, their turns measured over every sample between); FitError when fewer than
    ``fewest`` are left."""
    if keep.sum() < fewest:
        raise FitError(
            f"only {int(keep.sum())} samples outside disturbed fields: a field fit needs {fewest}; "
            "keep away from iron (doors, cars, magnets) while moving"
        )
    smaller, _ = ev.only(keep)

    def rows(value: np.ndarray | None) -> np.ndarray | None:
        return None if value is None else np.asarray(value)[keep]

    kept = dataclasses.replace(
        inp, mag=inp.mag[keep], acc=rows(inp.acc), gyr=rows(inp.gyr), vel_ned_ms=rows(inp.vel_ned_ms), disturbed=None
    )
    return kept, smaller, None if ev_motion is None else ev_motion.rows(keep)
