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
``field_disturbance`` judges a whole log (not yet applied by the fits: docs/compass.md, "Disturbances");
``magnet.attitude.field_watch.FieldWatch`` is the steps and magnitude checks causal, batch by batch, against
references of its own (the compass: a disturbed sample is not given to the filter, which then holds its heading on
the gyroscope).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence

import numpy as np

from magnet.attitude.field_watch import integrated_attitude, to_frame
from magnet.attitude.heading import dip_angle_deg, row_norm
from magnet.frames import quaternion_to_matrix


@dataclasses.dataclass(frozen=True)
class DisturbanceSettings:
    """Thresholds of the checks (see the module docstring): field_tol_pct % of the expected |B|; dip_tol_deg;
    steps ((window_s, threshold_ut), ...) between means over smooth_s (the noise averaged down); hold_s each side of
    a flagged sample; gravity_window_s the accelerometer's average in the gyroscope's frame (a swinging arm's
    centripetal pull and a car's turn do not average out: the dip is off by their tilt, so its tolerance is wide)."""

    field_tol_pct: float = 8.0
    dip_tol_deg: float = 10.0
    steps: tuple[tuple[float, float], ...] = ((0.25, 2.5), (2.0, 3.5))
    hold_s: float = 1.0
    gravity_window_s: float = 4.0
    smooth_s: float = 0.1

    def __post_init__(self) -> None:
        numbers = [self.field_tol_pct, self.dip_tol_deg, self.hold_s, self.gravity_window_s, self.smooth_s]
        numbers += [value for pair in self.steps for value in pair]
        if not all(np.isfinite(numbers)) or min(numbers) < 0 or any(len(pair) != 2 for pair in self.steps):
            raise ValueError("disturbance settings must be finite numbers >= 0 (steps: (window_s, threshold_ut))")


DEFAULT = DisturbanceSettings()


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


def _step_flags(changes: Sequence[tuple[np.ndarray, int, float]], n: int) -> np.ndarray:
    """Samples (N,) within a window whose change exceeds its threshold: (|change| (N - w,), w, threshold) each,
    change k comparing sample k + w with sample k."""
    flags = np.zeros(n, dtype=bool)
    for change, width, threshold in changes:
        over = np.flatnonzero(change > threshold)
        marks = np.zeros(n + 1, dtype=int)
        np.add.at(marks, over, 1)
        np.add.at(marks, np.minimum(over + width + 1, n), -1)
        flags |= np.cumsum(marks[:n]) > 0
    return flags


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
    reference_ut = float(np.median(norm)) if expected_ut is None and n else float(expected_ut or 0.0)
    finite_dip = dip[np.isfinite(dip)]
    reference_dip = (
        float(np.median(finite_dip)) if expected_dip_deg is None and finite_dip.size else float(expected_dip_deg or 0)
    )
    magnitude = np.abs(norm - reference_ut) > reference_ut * settings.field_tol_pct / 100.0
    with np.errstate(invalid="ignore"):
        dip_off = np.abs(dip - reference_dip) > settings.dip_tol_deg
    if expected_dip_deg is None and not finite_dip.size:
        dip_off = np.zeros(n, dtype=bool)
    smooth = max(1, round(settings.smooth_s / step_s))
    world = _moving_mean(to_frame(quat, field) if quat is not None else norm[:, None], smooth)
    changes = []
    for window_s, threshold in settings.steps:
        width = max(1, round(window_s / step_s))
        if width < n:
            change = world[width:] - world[:-width]
            changes.append((row_norm(change) if quat is not None else np.abs(change[:, 0]), width, threshold))
    step = _step_flags(changes, n)
    hold = round(settings.hold_s / step_s)
    disturbed = _widen(magnitude | dip_off | step, hold, hold)
    return FieldDisturbance(norm, dip, magnitude, dip_off, step, disturbed, reference_ut, reference_dip)
