"""The method table (``METHODS``: every method, turntable and gyro-ellipsoid included) and the entry points, each
taking one ``FitInput``: ``fit_shape`` (the fit alone) and ``fit`` (with quality and gate)."""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable

import numpy as np

from magnet.calibration import disturbed
from magnet.calibration.alignment import aligned, ellipsoid_align, needs_acc
from magnet.calibration.base import (
    GYROSCOPE_NEEDED,
    FitError,
    Method,
    Shape,
    check_acc,
    check_gyr,
    check_samples,
    holdout_mask,
)
from magnet.calibration.closed_form import minmax, minmax2d, sphere
from magnet.calibration.ellipsoid import ellipsoid
from magnet.calibration.fit_input import FitInput
from magnet.calibration.gyro_ellipsoid import gyro_ellipsoid
from magnet.calibration.turntable import fit_turntable
from magnet.model import Calibration, Quality
from magnet.quality import GateThresholds, Geometry, assess, gate, motion, ut_per_unit
from magnet.quality.stats import take_rows
from magnet.quality.units_hint import earth_range_refusal, unit_hint

#: the held-out fit of an iterative method stops when a step gains less than this fraction of its cost (the fit of
#: every sample: ``magnet.calibration.ellipsoid.TOLERANCE``); measured, its offset stays within 1e-4 uT of a fit to
#: the full tolerance from a cold start
HOLDOUT_TOLERANCE = 1e-9


def _closed(fn: Callable[[np.ndarray, np.ndarray | None, bool], Shape]) -> Callable[[FitInput], Shape]:
    """A method of (mag, acc, robust) as a method of the checked input, on its undisturbed rows."""

    def shape(data: FitInput) -> Shape:
        keep = disturbed.kept(data)
        if keep is None:
            return fn(data.mag, data.acc, data.robust_extremes)
        acc = None if data.acc is None else take_rows(data.acc, keep)
        return fn(take_rows(data.mag, keep), acc, data.robust_extremes)

    return shape


def _rates(data: FitInput) -> tuple[np.ndarray, float]:
    """The body rates (N, 3) rad/s and their period (s); FitError when the input has none."""
    if data.gyr_rads is None or data.period_s is None:
        raise FitError(GYROSCOPE_NEEDED)
    return np.asarray(data.gyr_rads, dtype=float), data.period_s


def _gyro_ellipsoid(data: FitInput) -> Shape:
    return gyro_ellipsoid(data.mag, *_rates(data), keep=disturbed.kept(data))


def _gyro_held_out(data: FitInput, whole: Shape, train: np.ndarray) -> Shape:
    """gyro-ellipsoid's held-out fit: its windows of consecutive samples are taken inside the kept blocks only."""
    return gyro_ellipsoid(data.mag, *_rates(data), keep=train)


def _ellipsoid_held_out(data: FitInput, whole: Shape, train: np.ndarray) -> Shape:
    """The ellipsoid's held-out fit: started from the fit of every sample, stopped at HOLDOUT_TOLERANCE."""
    return ellipsoid(take_rows(data.mag, train), None, data.robust_extremes, whole, HOLDOUT_TOLERANCE)


def _aligned_held_out(data: FitInput, whole: Shape, train: np.ndarray) -> Shape:
    """ellipsoid+align's held-out fit: its ellipsoid started as the ellipsoid's, then aligned on the same rows."""
    mag, acc = take_rows(data.mag, train), take_rows(needs_acc(data.acc), train)
    return aligned(ellipsoid(mag, acc, data.robust_extremes, whole, HOLDOUT_TOLERANCE), mag, acc)


def _turntable_shape(data: FitInput) -> Shape:
    raise FitError(TURNTABLE_NEEDED)


def _turntable(data: FitInput) -> Calibration:
    """The turntable's own fit, quality and gate (``magnet.calibration.turntable.fit_turntable``) from
    ``data.turntable``."""
    setup = data.turntable
    if setup is None:
        raise FitError(TURNTABLE_NEEDED)
    return fit_turntable(
        data.mag,
        setup.mounting,
        setup.heading_deg,
        setup.horizontal,
        setup.vertical,
        setup.variant,
        unit=data.unit,
        field_unit=setup.field_unit,
        gate_thresholds=data.gate,
    )


def _field_shape(data: FitInput) -> Shape:
    raise FitError("offset, offset+scale and planar are fitted by fit() (magnet.calibration.field), not as a shape")


def _field_rung(method: Method) -> Callable[[FitInput], Calibration]:
    """A rung of the field ladder (``magnet.calibration.field``) as a method that makes its own record. The ladder's
    modules are imported when a rung is fitted: a fit the ellipsoid makes (``magnet fit`` of a tumble) never loads
    them (a tenth of its start)."""

    def fit_rung(data: FitInput) -> Calibration:
        from magnet.calibration import field

        return field.fit_field(
            field.FieldInput.of(disturbed.judged(data)), rung=method.value, gate_thresholds=data.gate
        )

    return fit_rung


#: why the turntable method cannot fit samples alone
TURNTABLE_NEEDED = (
    "the turntable method needs the mounting and table angle of every sample and the known field: give FitInput's "
    "turntable (magnet fit: the mounting and heading_deg columns, --horizontal and --vertical; fit_turntable)"
)

#: (checked input, the shape fitted to every sample, the training rows (N,) bool) -> the shape of the training rows
HeldOut = Callable[[FitInput, Shape, np.ndarray], Shape]


@dataclasses.dataclass(frozen=True)
class MethodSpec:
    """A method in the table: ``shape``, its fit of the checked input; ``geometry``, what its samples are judged by;
    ``held_out``, its fit of the training rows (None: ``shape`` again on them alone); ``whole``, a method that makes
    its own record, quality and gate (turntable; None: ``fit``'s)."""

    shape: Callable[[FitInput], Shape]
    geometry: Geometry
    held_out: HeldOut | None = None
    whole: Callable[[FitInput], Calibration] | None = None


#: every method: how it fits, what its samples are judged by, how its held-out fit is made
METHODS: dict[Method, MethodSpec] = {
    Method.MINMAX2D: MethodSpec(_closed(minmax2d), Geometry.CIRCLE),
    Method.MINMAX: MethodSpec(_closed(minmax), Geometry.SPHERE),
    Method.SPHERE: MethodSpec(_closed(sphere), Geometry.SPHERE),
    Method.ELLIPSOID: MethodSpec(_closed(ellipsoid), Geometry.SPHERE, _ellipsoid_held_out),
    Method.ELLIPSOID_ALIGN: MethodSpec(_closed(ellipsoid_align), Geometry.SPHERE, _aligned_held_out),
    Method.TURNTABLE: MethodSpec(_turntable_shape, Geometry.TURNTABLE, whole=_turntable),
    Method.GYRO_ELLIPSOID: MethodSpec(_gyro_ellipsoid, Geometry.SPHERE, _gyro_held_out),
    **{
        rung: MethodSpec(_field_shape, Geometry.SPHERE, whole=_field_rung(rung))
        for rung in (Method.OFFSET, Method.OFFSET_SCALE, Method.PLANAR)
    },
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


def _checked(data: FitInput, method: Method) -> FitInput:
    """The input with its arrays checked for ``method`` (``magnet.calibration.base``); FitError naming the problem."""
    mag = check_samples(data.mag, method)
    acc = check_acc(data.acc, len(mag), method is Method.ELLIPSOID_ALIGN)
    rates = check_gyr(data.gyr_rads, data.period_s, len(mag), method is Method.GYRO_ELLIPSOID)
    field_ut = data.field_ut
    if field_ut is not None and not (math.isfinite(field_ut) and field_ut > 0):
        raise FitError(f"expected field strength must be a positive number of uT, got {field_ut!r}")
    return data.replace(mag=mag, acc=acc, gyr_rads=rates)


def fit_shape(data: FitInput, method: Method | str) -> tuple[Calibration, Shape]:
    """The fit alone, without quality or gate: (record with empty quality, the shape found). Raises FitError."""
    method = Method.parse(method)
    checked = _checked(data, method)
    shape = METHODS[method].shape(checked)
    keep = disturbed.kept(checked)
    count = len(checked.mag) if keep is None else int(keep.sum())
    return _finish(shape, method, data.unit, data.field_ut, count), shape


def fit(data: FitInput, method: Method | str) -> Calibration:
    """Fit a calibration to ``data`` (``FitInput``: raw samples mag (N, 3) in its unit, acc, gyr_rads, ...) with
    ``method``.

    The record is scaled to ``data.field_ut`` (None: the fitted radius) and carries ``quality``
    (``magnet.quality.assess``, including a held-out residual: every 5th block of 20 samples is left out of a
    second fit and scored) and ``accepted``/``reason`` from ``magnet.quality.gate`` (``data.gate`` None: default
    thresholds). With acc, the dip and the consistency figures of ``magnet.quality.motion``: gyr_rads sampled every
    period_s seconds gives the fused gravity and attitude, else the quasi-static samples are used; the fit must make
    the field more constant than ``data.reference`` (the calibration in force; None: no calibration) on held-out
    data. A method that makes its own record (turntable) is its own judge. Raises FitError when no calibration can
    be computed.
    """
    method = Method.parse(method)
    spec = METHODS[method]
    if spec.whole is not None:
        return spec.whole(data)
    if method is not Method.TURNTABLE:
        data = disturbed.judged(data)
    calibration, shape = fit_shape(data, method)
    mag = np.asarray(data.mag, dtype=float)
    acc_arr = None if data.acc is None else np.asarray(data.acc, dtype=float)
    gyr, period_s, unit, field_ut = data.gyr_rads, data.period_s, data.unit, data.field_ut
    keep = disturbed.kept(data)
    holdout, test = _held_out_rows(data.replace(mag=mag, acc=acc_arr), method, shape, keep)
    if keep is not None:  # the figures and the judgement on the undisturbed samples alone
        mag = take_rows(mag, keep)
    to_ut = ut_per_unit(unit)
    geometry = spec.geometry
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
        ev = _motion_evidence(acc_arr, gyr, period_s, len(acc_arr))  # in time order, every sample
        if keep is not None:
            ev = ev.rows(keep)
        quality = motion.with_motion_figures(quality, mag, calibration, ev, test, holdout, data.reference, corrected)
    if keep is not None:
        quality = quality.with_extra(disturbed_samples=int((~keep).sum()))
    if shape.note:
        quality = quality.with_extra(note=shape.note)
    if shape.mag_lag_s:  # the compass turns the field forward over it (magnet.attitude.mag_delay)
        quality = quality.with_extra(mag_lag_s=shape.mag_lag_s)
    accepted, reason = _gate(quality, data.gate, method)
    sphere = geometry is Geometry.SPHERE
    earth = earth_range_refusal(shape.radius, to_ut) if sphere and field_ut is None else None
    hint = unit_hint(shape.radius, to_ut, field_ut) if sphere and not accepted and not earth else None
    if earth:
        accepted, reason = False, earth if accepted else f"{earth}; {reason}"
    if hint:
        reason = f"{hint}; {reason}"
    if shape.note:
        reason = f"{reason}; {shape.note}"
    return calibration.replace(quality=quality, accepted=accepted, reason=reason)


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


def _held_out_rows(
    data: FitInput, method: Method, whole: Shape, keep: np.ndarray | None
) -> tuple[tuple[np.ndarray, Calibration] | None, np.ndarray]:
    """(``_holdout``'s result, the held-out rows among the kept ones): every HOLDOUT_EVERY-th block held out, the
    disturbed samples (``keep`` False) in neither set."""
    test = _holdout_mask(len(data.mag), data.period_s)
    if keep is None:
        return _holdout(data, method, whole, test), test
    return _holdout(data, method, whole, test & keep, ~test & keep), test[keep]


def _holdout_mask(count: int, period_s: float | None = None) -> np.ndarray:
    """(count,) bool: the held-out test set (``base.holdout_mask``: blocks of HOLDOUT_BLOCK_S seconds)."""
    return holdout_mask(count, period_s)


def _holdout(
    data: FitInput, method: Method, whole: Shape, test: np.ndarray, train: np.ndarray | None = None
) -> tuple[np.ndarray, Calibration] | None:
    """(test samples, calibration fitted on the training rows, by default the rest): every HOLDOUT_EVERY-th block of
    samples is the test set (``test``: ``_holdout_mask(len(mag), period_s)``, less the disturbed samples, which are in
    neither set); ``data``: the input, its mag and acc float arrays; None when the training rows cannot be fitted.

    ``whole``: the shape fitted to every sample. The iterative methods (``_warm``) start the held-out fit from it,
    and stop at HOLDOUT_TOLERANCE: the fit is still of the training samples alone (the same robust steps, the same
    minimum), found in fewer iterations (docs/front-door.md, "Fit speed": within 1e-4 uT of the cold fit, the
    held-out residual within 1e-5 uT). gyro-ellipsoid's windows stay inside the training blocks; the others are
    fitted again, checked, on the training rows alone."""
    train = ~test if train is None else train
    held_out = METHODS[method].held_out
    try:
        if held_out is not None:
            shape = held_out(data, whole, train)
        else:
            acc = None if data.acc is None else take_rows(data.acc, train)
            rows = FitInput(take_rows(data.mag, train), acc=acc, robust_extremes=data.robust_extremes)
            shape = METHODS[method].shape(_checked(rows, method))
    except FitError:
        return None
    return take_rows(data.mag, test), _finish(shape, method, data.unit, data.field_ut, int(train.sum()))
