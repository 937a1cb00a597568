"""The method table and the entry points: ``fit_shape`` (the fit alone) and ``fit`` (with quality and gate)."""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable

import numpy as np

from magnet.calibration import field
from magnet.calibration.alignment import ellipsoid_align
from magnet.calibration.base import GYROSCOPE_NEEDED, FitError, Method, Shape, check_acc, check_gyr, check_samples
from magnet.calibration.closed_form import minmax, minmax2d, sphere
from magnet.calibration.ellipsoid import ellipsoid
from magnet.calibration.gyro_ellipsoid import gyro_ellipsoid
from magnet.model import IDENTITY, Calibration, Quality
from magnet.quality import GateThresholds, Geometry, assess, gate, motion, ut_per_unit
from magnet.quality.stats import take_rows
from magnet.quality.units_hint import EARTH_MAX_UT, EARTH_MIN_UT, unit_hint

#: samples are taken in blocks of HOLDOUT_BLOCK; every HOLDOUT_EVERY-th block is held out to score the fit on data
#: it did not see (blocks, not single samples: neighbours in time are nearly the same reading)
HOLDOUT_BLOCK = 20
HOLDOUT_EVERY = 5
#: the held-out fit of an iterative method stops when a step gains less than this fraction of its cost (the fit of
#: every sample: ``magnet.calibration.ellipsoid.TOLERANCE``); measured, its offset stays within 1e-4 uT of a fit to
#: the full tolerance from a cold start
HOLDOUT_TOLERANCE = 1e-9


def _turntable(mag: np.ndarray, acc: np.ndarray | None, robust: bool) -> Shape:
    raise FitError(
        "the turntable method needs the mounting and table angle of every sample: use magnet.turntable.fit_turntable"
    )


def _no_gyroscope(mag: np.ndarray, acc: np.ndarray | None, robust: bool) -> Shape:
    raise FitError(GYROSCOPE_NEEDED)


def _field_only(mag: np.ndarray, acc: np.ndarray | None, robust: bool) -> Shape:
    raise FitError("offset, offset+scale and planar are fitted by fit() (magnet.calibration.field), not as a shape")


#: Method -> (shape function (mag, acc, robust) -> Shape, geometry the samples are judged by)
_METHODS: dict[Method, tuple[Callable[[np.ndarray, np.ndarray | None, bool], Shape], Geometry]] = {
    Method.MINMAX2D: (minmax2d, Geometry.CIRCLE),
    Method.MINMAX: (minmax, Geometry.SPHERE),
    Method.SPHERE: (sphere, Geometry.SPHERE),
    Method.ELLIPSOID: (ellipsoid, Geometry.SPHERE),
    Method.ELLIPSOID_ALIGN: (ellipsoid_align, Geometry.SPHERE),
    Method.TURNTABLE: (_turntable, Geometry.TURNTABLE),
    Method.GYRO_ELLIPSOID: (_no_gyroscope, Geometry.SPHERE),  # with a gyroscope: ``gyro_ellipsoid``
    Method.OFFSET: (_field_only, Geometry.SPHERE),  # the field ladder's rungs: ``magnet.calibration.field``
    Method.OFFSET_SCALE: (_field_only, Geometry.SPHERE),
    Method.PLANAR: (_field_only, Geometry.SPHERE),
}


def _finish(shape: Shape, method: Method, unit: str, field_ut: float | None, count: int) -> Calibration:
    """Scale the shape to the output unit (see the module docstring) and make the record."""
    to_ut = ut_per_unit(unit)
    if field_ut is not None and method is not Method.MINMAX2D:
        factor, output_unit, strength = field_ut / shape.radius, "ut", field_ut
    elif to_ut is not None:
        factor, output_unit, strength = to_ut, "ut", shape.radius * to_ut
    else:
        factor, output_unit, strength = 1.0, unit, shape.radius
    if method is Method.MINMAX2D:
        strength = 0.0  # the horizontal radius is not |B|: the total field is unknown from a level turn
    return Calibration(
        method=method.value,
        offset=shape.offset,
        matrix=shape.matrix * factor,
        field_strength=float(strength),
        sample_count=count,
        unit=unit,
        output_unit=output_unit,
        quality=Quality(extra={"mag_lag_s": shape.mag_lag_s}) if shape.mag_lag_s else Quality(),
    )


def fit_shape(
    mag: np.ndarray,
    method: Method | str,
    *,
    acc: np.ndarray | None = None,
    unit: str = "ut",
    field_ut: float | None = None,
    robust_extremes: bool = False,
    gyr: np.ndarray | None = None,
    period_s: float | None = None,
) -> tuple[Calibration, Shape]:
    """The fit alone, without quality or gate: (record with empty quality, the shape found). Raises FitError.

    gyr (N, 3) rad/s, consecutive samples every period_s seconds: used by ``gyro-ellipsoid`` (which needs them)."""
    method = Method.parse(method)
    mag = check_samples(mag, method)
    acc = check_acc(acc, len(mag), method is Method.ELLIPSOID_ALIGN)
    rates = check_gyr(gyr, period_s, len(mag), method is Method.GYRO_ELLIPSOID)
    if field_ut is not None and not (math.isfinite(field_ut) and field_ut > 0):
        raise FitError(f"expected field strength must be a positive number of uT, got {field_ut!r}")
    if method is Method.GYRO_ELLIPSOID and rates is not None and period_s is not None:
        shape = gyro_ellipsoid(mag, rates, period_s)
    else:
        shape = _METHODS[method][0](mag, acc, robust_extremes)
    return _finish(shape, method, unit, field_ut, len(mag)), shape


def fit(
    mag: np.ndarray,
    method: Method | str,
    *,
    acc: np.ndarray | None = None,
    unit: str = "ut",
    field_ut: float | None = None,
    gate: GateThresholds | None = None,
    robust_extremes: bool = False,
    gyr: np.ndarray | None = None,
    period_s: float | None = None,
    reference: Calibration | None = None,
    dip_deg: float | None = None,
) -> Calibration:
    """Fit a calibration to raw samples mag (N, 3) in ``unit``; acc (N, 3) specific force, any unit, or None.

    field_ut: the expected |B| in uT (WMM) or None (keep the fitted radius). Returns the record with ``quality``
    (``magnet.quality.assess``, including a held-out residual: every 5th block of 20 samples is left out of a
    second fit and scored) and ``accepted``/``reason`` from ``magnet.quality.gate`` (``gate=None``: default thresholds).
    With acc, the dip and the consistency figures of ``magnet.quality.motion``: gyr (N, 3) rad/s sampled every
    period_s seconds gives the fused gravity and attitude, else the quasi-static samples are used; the fit must make
    the field more constant than ``reference`` (the calibration in force; None: no calibration) on held-out data.
    Raises FitError when no calibration can be computed. dip_deg: the WMM's inclination (deg, positive down), the
    prior of the field ladder's rungs (offset, offset+scale, planar: ``magnet.calibration.field``), which keep the
    matrix of ``reference`` where they do not estimate it.
    """
    method = Method.parse(method)
    if method.field_rung:
        return field.fit_field(
            field.FieldInput(mag, acc, gyr, period_s, unit, field_ut, dip_deg, reference),
            rung=method.value,
            gate_thresholds=gate,
        )
    calibration, shape = fit_shape(
        mag, method, acc=acc, unit=unit, field_ut=field_ut, robust_extremes=robust_extremes, gyr=gyr, period_s=period_s
    )
    mag = np.asarray(mag, dtype=float)
    acc_arr = None if acc is None else np.asarray(acc, dtype=float)
    test = _holdout_mask(len(mag))
    if method is Method.GYRO_ELLIPSOID and gyr is not None and period_s is not None:
        holdout = _gyro_holdout(mag, np.asarray(gyr, dtype=float), period_s, unit, field_ut, test)
    else:
        holdout = _holdout(mag, method, acc_arr, unit, field_ut, robust_extremes, shape, test)
    to_ut = ut_per_unit(unit)
    geometry = _METHODS[method][1]
    corrected = calibration.apply(mag)  # for the figures of assess and of motion
    quality = assess(
        mag,
        calibration,
        corrected=corrected,
        geometry=geometry,
        acc=None,
        expected_field_ut=field_ut,
        fitted_radius_ut=shape.radius * to_ut if to_ut is not None and geometry is Geometry.SPHERE else None,
        holdout=holdout,
    )
    if acc_arr is not None and geometry is Geometry.SPHERE:
        ev = _motion_evidence(acc_arr, gyr, period_s, len(mag))
        figures = motion.motion_figures(
            mag,
            calibration,
            ev,
            test,
            holdout[1] if holdout else None,
            reference or IDENTITY,
            "the calibration in force" if reference else "no calibration",
            corrected,
        )
        quality = dataclasses.replace(quality, dip_spread_deg=figures.pop("dip_spread_deg")).with_extra(**figures)
    if shape.note:
        quality = quality.with_extra(note=shape.note)
    if shape.mag_lag_s:  # the compass turns the field forward over it (magnet.mag_delay)
        quality = quality.with_extra(mag_lag_s=shape.mag_lag_s)
    accepted, reason = _gate(quality, gate, method)
    earth = _outside_the_earth(shape.radius, to_ut, field_ut, geometry)
    advise = geometry is Geometry.SPHERE and (not accepted or earth is not None)
    hint = unit_hint(shape.radius, to_ut, field_ut) if advise else None
    if earth:
        earth = hint or earth
        accepted, reason, hint = False, earth if accepted else f"{earth}; {reason}", None
    if hint:
        reason = f"{hint}; {reason}"
    if shape.note:
        reason = f"{reason}; {shape.note}"
    return calibration.replace(quality=quality, accepted=accepted, reason=reason)


def _outside_the_earth(radius: float, to_ut: float | None, field_ut: float | None, geometry: Geometry) -> str | None:
    """Why a sphere's radius (declared unit; ``to_ut`` uT per unit, None for counts) can be no Earth field when no
    expected field is known (with one, the gate's radius check judges it): the total field at the surface lies in
    EARTH_MIN_UT..EARTH_MAX_UT everywhere, so a radius outside it is a wrong unit (gauss read as uT: 0.5 "uT")."""
    if field_ut is not None or to_ut is None or geometry is not Geometry.SPHERE or not np.isfinite(radius):
        return None
    radius_ut = radius * to_ut
    if EARTH_MIN_UT <= radius_ut <= EARTH_MAX_UT:
        return None
    return (
        f"fitted radius {radius_ut:.3g} uT is no Earth field ({EARTH_MIN_UT:g}-{EARTH_MAX_UT:g} uT anywhere at the "
        "surface): the samples are in another unit than declared (--unit)"
    )


def _motion_evidence(acc: np.ndarray, gyr: np.ndarray | None, period_s: float | None, n: int) -> motion.MotionEvidence:
    if gyr is not None and np.shape(gyr) != (n, 3):
        raise FitError(f"gyr must have the shape of the magnetometer samples ({n}, 3), got {np.shape(gyr)}")
    try:
        return motion.evidence(acc, gyr, period_s)
    except ValueError as exc:
        raise FitError(str(exc)) from None


def _gate(quality: Quality, thresholds: GateThresholds | None, method: Method) -> tuple[bool, str]:
    """The gate; gyro-ellipsoid is not asked for coverage: the gyroscope's turns determine it, not the shape of the
    cloud (a vehicle's figure-8 covers 40 %), and the fit refuses turns that leave it undetermined."""
    chosen = thresholds or GateThresholds()
    if method is Method.GYRO_ELLIPSOID:
        chosen = dataclasses.replace(chosen, min_coverage=0.0)
    return gate(quality, chosen)


def _holdout_mask(count: int) -> np.ndarray:
    """(count,) bool: every HOLDOUT_EVERY-th block of HOLDOUT_BLOCK samples, the held-out test set."""
    period = np.arange(HOLDOUT_BLOCK * HOLDOUT_EVERY) // HOLDOUT_BLOCK == HOLDOUT_EVERY - 1
    return np.resize(period, count)  # the pattern repeats every HOLDOUT_EVERY blocks


def _holdout(
    mag: np.ndarray,
    method: Method,
    acc: np.ndarray | None,
    unit: str,
    field_ut: float | None,
    robust: bool,
    whole: Shape | None = None,
    test: np.ndarray | None = None,
) -> tuple[np.ndarray, Calibration] | None:
    """(test samples, calibration fitted on the rest): every HOLDOUT_EVERY-th block of samples is the test set.

    ``whole``: the shape fitted to every sample. The iterative methods (``_WARM_STARTED``) start the held-out fit
    from it, and stop at HOLDOUT_TOLERANCE: the fit is still of the training samples alone (the same robust steps,
    the same minimum), found in fewer iterations (docs/front-door.md, "Fit speed": within 1e-4 uT of the cold fit,
    the held-out residual within 1e-5 uT). ``test``: ``_holdout_mask(len(mag))``, when the caller has it already."""
    test = _holdout_mask(len(mag)) if test is None else test
    train = ~test
    train_acc = None if acc is None or method not in _READS_ACC else take_rows(acc, train)  # the others never use it
    try:
        if whole is not None and method in _WARM_STARTED:
            shape = _WARM_STARTED[method](take_rows(mag, train), train_acc, robust, whole, HOLDOUT_TOLERANCE)
            train_cal = _finish(shape, method, unit, field_ut, int(train.sum()))
        else:
            train_cal, _ = fit_shape(
                take_rows(mag, train), method, acc=train_acc, unit=unit, field_ut=field_ut, robust_extremes=robust
            )
    except FitError:
        return None
    return take_rows(mag, test), train_cal


def _gyro_holdout(
    mag: np.ndarray, gyr: np.ndarray, period_s: float, unit: str, field_ut: float | None, test: np.ndarray
) -> tuple[np.ndarray, Calibration] | None:
    """``_holdout`` for gyro-ellipsoid: its windows of consecutive samples are taken inside the kept blocks only."""
    try:
        shape = gyro_ellipsoid(mag, gyr, period_s, keep=~test)
    except FitError:
        return None
    return take_rows(mag, test), _finish(shape, Method.GYRO_ELLIPSOID, unit, field_ut, int((~test).sum()))


#: the methods whose shape depends on the accelerometer's samples
_READS_ACC = frozenset({Method.ELLIPSOID_ALIGN})
#: methods whose held-out fit starts from the fit of every sample: (mag, acc, robust, start, tolerance) -> Shape
_WARM_STARTED: dict[Method, Callable[[np.ndarray, np.ndarray | None, bool, Shape, float], Shape]] = {
    Method.ELLIPSOID: ellipsoid,
    Method.ELLIPSOID_ALIGN: ellipsoid_align,
}
