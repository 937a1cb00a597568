"""Headings from the field and the accelerometer, for many samples of many devices at once, and their smoothing.

``compute_headings`` turns the corrected field into a tilt-compensated heading (level where a sample has no
accelerometer); ``smooth_tail`` is the circular sliding mean carried across batches.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from magnet.attitude import heading as hd


@dataclasses.dataclass(frozen=True, eq=False)
class Headings:
    """Headings of S samples: field_ut (S, 3) corrected uT, heading_deg (S,) magnetic, pitch_deg and roll_deg (S,)
    (0 without acc), flags (S,) ``HeadingFlag`` bits."""

    field_ut: np.ndarray
    heading_deg: np.ndarray
    pitch_deg: np.ndarray
    roll_deg: np.ndarray
    flags: np.ndarray


def compute_headings(field: np.ndarray, acc_ms2: np.ndarray, calibrated: np.ndarray) -> Headings:
    """Headings for S samples of any devices at once; flags: CALIBRATED only (the disturbance checks come after the
    attitude is known, ``magnet.attitude.heading.disturbance_flags``).

    field (S, 3) uT corrected (``magnet.compass.calibrations.Correction``); acc_ms2 (S, 3) m/s^2 with NaN rows where
    a sample has no accelerometer; calibrated (S,) bool: whether the sample's device has a calibration in force.
    """
    has_acc = hd.rows_finite(acc_ms2)
    with np.errstate(invalid="ignore", divide="ignore"):
        tilted = hd.tilt_compensated_heading_deg(field, acc_ms2)
        pitch, roll = hd.pitch_roll_deg(acc_ms2)
    tilt_known = has_acc & np.isfinite(tilted)
    heading = tilted  # the level heading only where there is no tilt (most samples have one)
    if not tilt_known.all():
        heading = np.where(tilt_known, tilted, hd.level_heading_deg(field))
    flags = np.where(calibrated, int(hd.HeadingFlag.CALIBRATED), 0).astype(np.int64)
    return Headings(field, heading, np.where(has_acc, pitch, 0.0), np.where(has_acc, roll, 0.0), flags)


def smooth_tail(tail: np.ndarray, heading_deg: np.ndarray, window: int) -> tuple[np.ndarray, np.ndarray]:
    """Circular sliding mean over ``window`` headings across batches: (smoothed (N,), the new tail to keep).

    tail: the last ``window - 1`` headings (deg) of the previous batches of the device; heading_deg (N,) deg."""
    if window == 1:
        return heading_deg, tail[:0]
    joined = np.concatenate([tail, heading_deg])
    return hd.smooth_heading_deg(joined, window)[-heading_deg.size :], joined[-(window - 1) :]


def batches_with(mask: np.ndarray, counts: np.ndarray) -> list[bool]:
    """Per batch (counts (B,) samples each, in order), whether any of its samples is set in ``mask`` (S,) bool."""
    out = np.zeros(len(counts), dtype=bool)
    nonempty = counts > 0
    if mask.any() and nonempty.any():
        starts = np.concatenate([[0], np.cumsum(counts)[:-1]])
        out[nonempty] = np.logical_or.reduceat(mask, starts[nonempty])
    return out.tolist()
