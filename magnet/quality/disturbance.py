"""Which samples of a field are disturbed: |B| or dip away from the expected, or a change the rotation does not explain.

A magnetic disturbance (a steel door, a parked car, a magnet) adds a field fixed in the world to the Earth's. Three
checks find it in a calibrated field (docs/compass.md, "Disturbances"):

- magnitude: | |B| - F | > ``field_tol_pct`` % of F, F the expected strength (the WMM at the place, or the median
  |B| of the samples when none is given);
- dip: | dip - I | > ``dip_tol_deg``, dip the angle of the field below the horizon, I the expected inclination (or
  the median dip). The horizon comes from gravity: with a gyroscope, the accelerometer averaged over
  ``gravity_window_s`` in the gyroscope's frame (a walker's steps and a swinging arm average out: the trick of vqf's
  tilt filter), else the accelerometer itself;
- steps: with a gyroscope the field is turned into the frame the gyroscope's integration holds still, where the
  Earth's field is constant: w_k = Q_k b_k (Q_k the attitude integrated from the first sample). A change of w over
  a window (``steps``: (window_s, threshold_ut) pairs, a short one for sudden steps and a long one for slow ones) the
  rotation does not explain is a disturbance coming or going: it catches a change of the field's *direction* in the
  horizontal plane, which neither |B| nor dip sees and which is the one that turns the heading. Without a
  gyroscope the step checks |B| alone. A calibration's leftover offset e shows here as about |e| x the angle turned
  within the window, so the field must be corrected first (the record at hand, or the fit being judged).

Flagged samples are widened by ``hold_s`` on both sides (a disturbance fades in and out below the thresholds).
``field_disturbance`` judges a whole log; ``magnet.attitude.field_watch.FieldWatch`` is the steps and magnitude
checks causal, batch by batch, against references of its own (the compass and ``magnet heading``: a disturbed sample
is not given to the filter, which then holds its heading on the gyroscope). Both take their step windows, floors and
|B| tolerance from ``field_watch`` (``STEPS``, ``FIELD_TOL_PCT``, ``SMOOTH_S``): one definition.

The fits (``disturbed_samples``, docs/field-calibration.md, "Disturbed samples"): with a correction (the record in
force, or a first fit) the checks above with the WMM's |B| and dip, the steps judged against the level the correction
usually leaves (``relative``: a leftover offset e shows as about |e| x the angle turned, as in the watch); without
one, what the raw field can tell: a hard iron turns with the body, so whatever the offset, the raw field changes
within a window by at most the sensor's gain x |B| x the angle the gyroscope turned (``raw_steps``), and a larger
change is a field that moved (a door, a car).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence

import numpy as np

from magnet.attitude.field_watch import FIELD_TOL_PCT, SMOOTH_S, STEPS, TURN_FLOOR_RAD, integrated_attitude, to_frame
from magnet.attitude.heading import dip_angle_deg, row_norm
from magnet.frames import quaternion_to_matrix
from magnet.model import Calibration
from magnet.order_stats import median, quantile
from magnet.units import EARTH_MAX_UT, ut_per_unit


@dataclasses.dataclass(frozen=True)
class DisturbanceSettings:
    """Thresholds of the checks (see the module docstring): field_tol_pct % of the expected |B|; dip_tol_deg;
    steps ((window_s, threshold_ut), ...) between means over smooth_s (the noise averaged down); hold_s each side of
    a flagged sample; gravity_window_s the accelerometer's average in the gyroscope's frame (a swinging arm's
    centripetal pull and a car's turn do not average out: the dip is off by their tilt, so its tolerance is wide);
    relative: None (the thresholds are the tolerances and the floors) or: | |B| - F | and | dip - I | are flagged
    only beyond ``relative`` x their 75th percentile over the log too, and, with a gyroscope, a step only above
    ``relative`` x its usual level (the 75th percentile over the log of change per radian turned within the window,
    + turn_floor_rad) x the radians turned (+ turn_floor_rad), and above its floor: a correction's leftover error
    shows as steps in proportion to the turning, and is not a disturbance (the watch's rule, over a whole log)."""

    field_tol_pct: float = FIELD_TOL_PCT
    dip_tol_deg: float = 10.0
    steps: tuple[tuple[float, float], ...] = STEPS
    hold_s: float = 1.0
    gravity_window_s: float = 4.0
    smooth_s: float = SMOOTH_S
    relative: float | None = None
    turn_floor_rad: float = TURN_FLOOR_RAD

    def __post_init__(self) -> None:
        numbers = [self.field_tol_pct, self.dip_tol_deg, self.hold_s, self.gravity_window_s, self.smooth_s]
        numbers += [self.turn_floor_rad] + ([] if self.relative is None else [self.relative])
        numbers += [value for pair in self.steps for value in pair]
        if not all(np.isfinite(numbers)) or min(numbers) < 0 or any(len(pair) != 2 for pair in self.steps):
            raise ValueError("disturbance settings must be finite numbers >= 0 (steps: (window_s, threshold_ut))")


DEFAULT = DisturbanceSettings()
#: the fits' checks: the steps judged against the level the correction usually leaves (``relative``)
FIT = DisturbanceSettings(relative=4.0)
#: without a correction: the raw field changes within a window by at most this many times |B| x the radians turned
#: (the sensor's gains: a phone's soft iron is within 0.7-1.3, a field strength within the WMM's few %)
RAW_GAIN = 1.5


@dataclasses.dataclass(frozen=True, eq=False)
class FieldDisturbance:
    """Per sample (N,): norm_ut |B|; dip_deg (NaN without an accelerometer); magnitude, dip, step (bool) each check's
    verdict; disturbed (bool) any of them, widened by ``hold_s``; expected_ut and expected_dip_deg the references
    used (the given ones, or the samples' medians)."""

    norm_ut: np.ndarray
    dip_deg: np.ndarray
    magnitude: np.ndarray
    dip: np.ndarray
    step: np.ndarray
    disturbed: np.ndarray
    expected_ut: float
    expected_dip_deg: float


def _moving_mean(values: np.ndarray, width: int) -> np.ndarray:
    """Centred moving mean (N, 3) over ``width`` samples (shorter at the ends)."""
    if width <= 1 or len(values) == 0:
        return values
    sums = np.concatenate([np.zeros((1, values.shape[1])), np.cumsum(values, axis=0)])
    n = len(values)
    lo = np.clip(np.arange(n) - width // 2, 0, n)
    hi = np.clip(np.arange(n) + (width - width // 2), 0, n)
    return (sums[hi] - sums[lo]) / (hi - lo)[:, None]


def _widen(flags: np.ndarray, before: int, after: int) -> np.ndarray:
    """flags (N,) widened: a sample is set when a set one lies within ``before`` samples after it or ``after``
    samples before it."""
    if not flags.any() or (before <= 0 and after <= 0):
        return flags
    counts = np.concatenate([[0], np.cumsum(flags)])
    n = len(flags)
    index = np.arange(n)
    lo, hi = np.clip(index - after, 0, n), np.clip(index + before + 1, 0, n)
    return counts[hi] - counts[lo] > 0


def _path_rad(gyr_rads: np.ndarray, period_s: float) -> np.ndarray:
    """(N + 1,) the radians the gyroscope turned from the start to before each sample (and after the last)."""
    rates = row_norm(gyr_rads) * period_s
    return np.concatenate([[0.0], np.cumsum(rates)])


def _turned(path: np.ndarray, width: int, smooth: int) -> np.ndarray:
    """(N - width,) radians turned between sample k and k + width, each widened by the means' ``smooth`` samples."""
    n = len(path) - 1
    k = np.arange(n - width)
    lo = np.clip(k - smooth, 0, n)
    hi = np.clip(k + width + smooth + 1, 0, n)
    return path[hi] - path[lo]


def _step_flags(changes: Sequence[tuple[np.ndarray, int, float | np.ndarray]], n: int) -> np.ndarray:
    """Samples (N,) within a window whose change exceeds its threshold: (|change| (N - w,), w, threshold (one, or
    one per change)) each, change k comparing sample k + w with sample k."""
    flags = np.zeros(n, dtype=bool)
    for change, width, threshold in changes:
        over = np.flatnonzero(change > threshold)
        marks = np.zeros(n + 1, dtype=int)
        np.add.at(marks, over, 1)
        np.add.at(marks, np.minimum(over + width + 1, n), -1)
        flags |= np.cumsum(marks[:n]) > 0
    return flags


def _off_expected(
    norm: np.ndarray, dip: np.ndarray, reference_ut: float, reference_dip: float, settings: DisturbanceSettings
) -> tuple[np.ndarray, np.ndarray]:
    """(|B| off (N,), dip off (N,)): beyond the tolerances, and with ``relative`` beyond that many times the 75th
    percentile of the deviations too (what the correction usually leaves)."""
    deviation_ut = np.abs(norm - reference_ut)
    dip_deviation = np.abs(dip - reference_dip)
    field_tol, dip_tol = reference_ut * settings.field_tol_pct / 100.0, settings.dip_tol_deg
    if settings.relative is not None and len(norm):
        field_tol = max(field_tol, settings.relative * quantile(deviation_ut, 0.75))
        if np.isfinite(dip_deviation).any():
            dip_tol = max(dip_tol, settings.relative * quantile(dip_deviation[~np.isnan(dip_deviation)], 0.75))
    with np.errstate(invalid="ignore"):
        return deviation_ut > field_tol, dip_deviation > dip_tol


def _rotation_steps(
    field: np.ndarray,
    norm: np.ndarray,
    gyr_rads: np.ndarray | None,
    quat: np.ndarray | None,
    step_s: float,
    settings: DisturbanceSettings,
) -> np.ndarray:
    """(N,) bool: the steps check (module docstring) of the field (N, 3) with |B| norm (N,), in the gyroscope's
    integrated frame (quat (N, 4)) or, without one, of |B|."""
    n = len(field)
    smooth = max(1, round(settings.smooth_s / step_s))
    world = _moving_mean(to_frame(quat, field) if quat is not None else norm[:, None], smooth)
    path = _path_rad(np.asarray(gyr_rads, dtype=float), step_s) if gyr_rads is not None else None
    changes = []
    for window_s, floor in settings.steps:
        width = max(1, round(window_s / step_s))
        if width < n:
            change = world[width:] - world[:-width]
            size = row_norm(change) if quat is not None else np.abs(change[:, 0])
            threshold: float | np.ndarray = floor
            if settings.relative is not None and path is not None:
                turned = _turned(path, width, smooth) + settings.turn_floor_rad
                level = quantile(size / turned, 0.9)
                threshold = np.maximum(floor, settings.relative * level * turned)
            changes.append((size, width, threshold))
    return _step_flags(changes, n)


def field_disturbance(
    field_ut: np.ndarray,
    *,
    acc_ms2: np.ndarray | None = None,
    gyr_rads: np.ndarray | None = None,
    period_s: float | None = None,
    expected_ut: float | None = None,
    expected_dip_deg: float | None = None,
    settings: DisturbanceSettings = DEFAULT,
) -> FieldDisturbance:
    """The disturbed samples of a whole log (see the module docstring). field_ut (N, 3) the corrected field in the
    body frame, uT; acc_ms2 (N, 3) specific force (for the dip); gyr_rads (N, 3) body rates with ``period_s`` (for
    the gravity average and the rotation-compensated steps); expected_ut, expected_dip_deg the WMM's at the place,
    or None for the samples' medians."""
    field = np.asarray(field_ut, dtype=float)
    n = len(field)
    if field.ndim != 2 or field.shape[1] != 3:
        raise ValueError(f"field_ut must have shape (N, 3), got {field.shape}")
    gyro = gyr_rads is not None
    if gyro and (period_s is None or not np.isfinite(period_s) or period_s <= 0):
        raise ValueError("gyr_rads needs period_s, the sample period in seconds (> 0)")
    step_s = float(period_s) if period_s else 0.01
    quat = integrated_attitude(np.asarray(gyr_rads, dtype=float), step_s) if gyro else None
    norm = row_norm(field)
    dip = np.full(n, np.nan)
    if acc_ms2 is not None:
        acc = np.asarray(acc_ms2, dtype=float)
        if quat is not None:  # gravity: the accelerometer averaged where the gyroscope holds the frame still
            width = round(settings.gravity_window_s / step_s)
            averaged = _moving_mean(to_frame(quat, acc), width)
            acc = np.einsum("nji,nj->ni", quaternion_to_matrix(quat), averaged)
        dip = dip_angle_deg(field, acc)
    reference_ut = median(norm) if expected_ut is None and n else float(expected_ut or 0.0)
    finite_dip = dip[np.isfinite(dip)]
    reference_dip = median(finite_dip) if expected_dip_deg is None and finite_dip.size else float(expected_dip_deg or 0)
    magnitude, dip_off = _off_expected(norm, dip, reference_ut, reference_dip, settings)
    if expected_dip_deg is None and not finite_dip.size:
        dip_off = np.zeros(n, dtype=bool)
    step = _rotation_steps(field, norm, gyr_rads, quat, step_s, settings)
    hold = round(settings.hold_s / step_s)
    disturbed = _widen(magnitude | dip_off | step, hold, hold)
    return FieldDisturbance(norm, dip, magnitude, dip_off, step, disturbed, reference_ut, reference_dip)


def raw_steps(
    raw_ut: np.ndarray,
    gyr_rads: np.ndarray | None,
    period_s: float | None,
    field_ut: float | None = None,
    settings: DisturbanceSettings = FIT,
) -> np.ndarray:
    """(N,) bool: the samples of an uncorrected field raw_ut (N, 3) uT a moving field changes (module docstring).
    The offset turns with the body, so over a window the raw field changes by at most RAW_GAIN x F x the radians the
    gyroscope gyr_rads (N, 3) turned (F: field_ut, else the Earth's largest); a change of the means over ``smooth_s``
    beyond that and the step's floor is flagged, widened by ``hold_s``. Without a gyroscope, a change beyond 2 x
    RAW_GAIN x F (no rotation makes it)."""
    raw = np.asarray(raw_ut, dtype=float)
    n = len(raw)
    strength = float(field_ut) if field_ut else EARTH_MAX_UT
    step_s = float(period_s) if period_s else 0.01
    smooth = max(1, round(settings.smooth_s / step_s))
    means = _moving_mean(raw, smooth)
    path = _path_rad(np.asarray(gyr_rads, dtype=float), step_s) if gyr_rads is not None and period_s else None
    changes = []
    for window_s, floor in settings.steps:
        width = max(1, round(window_s / step_s))
        if width >= n:
            continue
        size = row_norm(means[width:] - means[:-width])
        if path is None:
            bound: float | np.ndarray = 2.0 * RAW_GAIN * strength
        else:
            bound = np.minimum(RAW_GAIN * strength * _turned(path, width, smooth), 2.0 * RAW_GAIN * strength)
        changes.append((size, width, bound + floor))
    hold = round(settings.hold_s / step_s)
    return _widen(_step_flags(changes, n), hold, hold)


def disturbed_samples(
    raw: np.ndarray,
    unit: str = "ut",
    *,
    acc: np.ndarray | None = None,
    gyr_rads: np.ndarray | None = None,
    period_s: float | None = None,
    correction: Calibration | None = None,
    expected_ut: float | None = None,
    expected_dip_deg: float | None = None,
) -> np.ndarray:
    """(N,) bool: the raw samples (N, 3) in ``unit`` that are disturbed, and that no fit takes (the module docstring;
    docs/field-calibration.md). With a ``correction`` to uT (the record in force, or a first fit): ``field_disturbance``
    of the corrected field with ``FIT``'s settings, |B| and dip against expected_ut and expected_dip_deg (the WMM's;
    None: the samples' medians); without one: ``raw_steps``. Without a gyroscope the samples need not be in time order
    (a calibrator's sphere cells): |B| and dip alone with a correction, nothing without one; nothing either where the
    unit does not convert to uT and no correction does."""
    samples = np.asarray(raw, dtype=float)
    acc_arr = None if acc is None else np.asarray(acc, dtype=float)
    gyr = None if gyr_rads is None or not period_s else np.asarray(gyr_rads, dtype=float)
    if correction is not None and correction.output_unit == "ut" and correction.unit == unit:
        field = correction.apply(samples)
        found = field_disturbance(
            field,
            acc_ms2=acc_arr,
            gyr_rads=gyr,
            period_s=period_s if gyr is not None else None,
            expected_ut=expected_ut,
            expected_dip_deg=expected_dip_deg,
            settings=FIT,
        )
        return found.disturbed if gyr is not None else found.magnitude | found.dip
    to_ut = ut_per_unit(unit)
    if to_ut is None or gyr is None:
        return np.zeros(len(samples), dtype=bool)
    return raw_steps(samples * to_ut, gyr, period_s, expected_ut)
