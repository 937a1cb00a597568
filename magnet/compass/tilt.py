"""Headings from the field and the accelerometer, for many samples of many devices at once, and their smoothing.

``compute_headings`` turns the corrected field into a tilt-compensated heading (level where a sample has no
accelerometer) for the samples the filters did not fuse; ``smooth_tail`` is the circular sliding mean carried across
batches (``Smoothing`` keeps each device's tail across steps); ``merge`` puts the filters' fused attitude in place
of the tilt one.
"""

from __future__ import annotations

import dataclasses
from typing import TYPE_CHECKING

import numpy as np

from magnet.attitude import heading as hd
from magnet.bounded import Recent

if TYPE_CHECKING:
    from magnet.compass.filters import FusedColumns


@dataclasses.dataclass(frozen=True, eq=False)
class Headings:
    """Headings of S samples: field_ut (S, 3) corrected uT, heading_deg (S,) magnetic, pitch_deg and roll_deg (S,)
    (0 without acc), flags (S,) ``HeadingFlag`` bits."""

    field_ut: np.ndarray
    heading_deg: np.ndarray
    pitch_deg: np.ndarray
    roll_deg: np.ndarray
    flags: np.ndarray


def field_flags(
    filter_field: np.ndarray, field: np.ndarray, calibrated: np.ndarray, expected_ut: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """(the field (S, 3) uT the filters get, the flags (S,) int64 ``HeadingFlag`` bits): CALIBRATED where
    ``calibrated`` (S,) bool; where a sample is uncalibrated and its corrected ``field`` (S, 3) uT is no Earth field
    (``expected_ut`` (S,) uT, NaN where unknown), FIELD_DISTURBED and a zero row for the filter
    (``magnet.attitude.heading.leave_out_no_earth_field``). The disturbance checks come after the attitude is known
    (``magnet.attitude.heading.disturbance_flags``)."""
    flags = np.where(calibrated, int(hd.HeadingFlag.CALIBRATED), 0).astype(np.int64)
    return hd.leave_out_no_earth_field(filter_field, field, flags, ~calibrated, expected_ut)


def compute_headings(field: np.ndarray, acc_ms2: np.ndarray, flags: np.ndarray, fused: np.ndarray) -> Headings:
    """Headings for S samples of any devices at once, from the accelerometer's tilt where a sample was not fused.

    field (S, 3) uT corrected (``magnet.compass.calibrations.Correction``); acc_ms2 (S, 3) m/s^2 with NaN rows where
    a sample has no accelerometer; flags (S,) int64 (``field_flags``), kept as they are; fused (S,) bool: the
    samples whose device's filter gave their attitude (``filters.FusedColumns.fused``), whose heading, pitch and roll
    ``merge`` puts in: NaN here, the tilt worked out only for the other samples (none when all were fused).
    """
    if not fused.any():
        heading, pitch, roll = _tilt_figures(field, acc_ms2)
        return Headings(field, heading, pitch, roll, flags)
    heading, pitch, roll = np.full((3, len(fused)), np.nan)
    rest = ~fused
    if rest.any():
        heading[rest], pitch[rest], roll[rest] = _tilt_figures(field[rest], acc_ms2[rest])
    return Headings(field, heading, pitch, roll, flags)


def _tilt_figures(field: np.ndarray, acc_ms2: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Magnetic heading, pitch and roll (n,) deg of n samples, each from its own field and accelerometer (n, 3):
    tilt-compensated where the accelerometer gives a tilt, else level (pitch and roll 0)."""
    has_acc = hd.rows_finite(acc_ms2)
    with np.errstate(invalid="ignore", divide="ignore"):
        tilted = hd.tilt_compensated_heading_deg(field, acc_ms2)
        pitch, roll = hd.pitch_roll_deg(acc_ms2)
    tilt_known = has_acc & np.isfinite(tilted)
    heading = tilted  # the level heading only where there is no tilt (most samples have one)
    if not tilt_known.all():
        heading = np.where(tilt_known, tilted, hd.level_heading_deg(field))
    return heading, np.where(has_acc, pitch, 0.0), np.where(has_acc, roll, 0.0)


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


def merge(headings: Headings, fused: FusedColumns) -> tuple[Headings, np.ndarray | None]:
    """The compass's headings (``magnet.compass.Headings``, S samples) with the fused attitude where there is one
    (flag FUSED; FIELD_DISTURBED also where vqf detects a disturbance; the other flags kept), and the fused attitude
    (S, 4) body -> magnetic NED, NaN rows where not fused, or None when no sample was fused (accelerometer tilt
    gives no quaternion, which keeps the messages of devices without a gyroscope as they were)."""
    f = fused.fused
    if not f.any():
        return headings, None
    disturbed = np.where(fused.mag_disturbed, int(hd.HeadingFlag.FIELD_DISTURBED), 0)
    flags = np.where(f, np.asarray(headings.flags) | int(hd.HeadingFlag.FUSED) | disturbed, headings.flags)
    return dataclasses.replace(
        headings,
        heading_deg=np.where(f, fused.heading_deg, headings.heading_deg),
        pitch_deg=np.where(f, fused.pitch_deg, headings.pitch_deg),
        roll_deg=np.where(f, fused.roll_deg, headings.roll_deg),
        flags=flags,
    ), fused.quat_wxyz


class Smoothing:
    """The circular sliding mean over ``window`` headings per device, across steps (tails of at most
    ``max_devices`` devices)."""

    def __init__(self, window: int, max_devices: int) -> None:
        self.window = window
        self.tails: Recent[str, np.ndarray] = Recent(max_devices)

    def apply(self, devices: list[str], bounds: list[int], heading_deg: np.ndarray) -> np.ndarray:
        if self.window == 1:
            return heading_deg
        parts = []
        for i, device in enumerate(devices):
            tail = self.tails.get(device)
            smoothed, self.tails[device] = smooth_tail(
                np.empty(0) if tail is None else tail, heading_deg[bounds[i] : bounds[i + 1]], self.window
            )
            parts.append(smoothed)
        return np.concatenate(parts or [np.empty(0)])
