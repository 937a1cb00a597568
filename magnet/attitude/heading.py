"""Heading, pitch and roll from a (calibrated) magnetometer and an accelerometer, vectorized over samples.

Conventions (docs/design.md, "Conventions"): body x forward, y right, z down. ``acc`` is specific force in m/s^2
(any unit works where only directions matter): a level, still device reads (0, 0, -g). Pitch is positive nose up, roll
positive right side down. Heading is in degrees [0, 360), clockwise from north, of the body x axis; magnetic heading
comes from the field, true heading = magnetic + declination (east positive, seed 001 eq. 1).

Every function takes arrays of shape (..., 3) (a single (3,) sample works too) and returns shape (...).
"""

from __future__ import annotations

import enum
import math

import numpy as np
import numpy.typing as npt

from magnet import _kernels
from magnet.units import EARTH_MAX_UT, EARTH_MIN_UT

#: below this fraction of the norm a vector is treated as missing (no tilt, no horizontal field)
_TINY = 1e-12


class HeadingFlag(enum.IntFlag):
    """Flags carried by each heading (bit values are part of the wire format)."""

    NONE = 0
    CALIBRATED = 1  # a calibration was applied
    NO_TILT = 2  # no usable accelerometer sample: heading assumes the device is level
    FIELD_DISTURBED = 4  # |B| is far from the expected field strength (magnet, iron or bad calibration nearby)
    DIP_DISTURBED = 8  # the angle between field and gravity is far from the expected inclination
    FUSED = 16  # attitude from the gyroscope-aided filter (magnet.attitude.fusion); without it, accelerometer tilt


def wrap_deg(angle_deg: npt.ArrayLike) -> np.ndarray:
    """Angles wrapped to [0, 360)."""
    angle = np.asarray(angle_deg, dtype=float)
    if angle.size and angle.min() >= -360.0 and angle.max() < 360.0:  # (atan2's range): np.mod's very numbers, as
        wrapped = (angle < 0).astype(float)  # it adds 360 to a negative remainder and fmod leaves these as they are
        wrapped *= 360.0  # (-0.0 + 0.0 is +0.0, as np.mod gives), at a tenth of its cost
        wrapped += angle
    else:
        wrapped = np.mod(angle, 360.0)
    return np.where(wrapped >= 360.0, 0.0, wrapped)  # mod of a tiny negative number can round up to 360


def angle_difference_deg(a_deg: npt.ArrayLike, b_deg: npt.ArrayLike) -> np.ndarray:
    """Signed difference a - b wrapped to [-180, 180): the right way to compare two headings."""
    return np.mod(np.asarray(a_deg, dtype=float) - np.asarray(b_deg, dtype=float) + 180.0, 360.0) - 180.0


def pitch_roll_deg(acc: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Pitch and roll (degrees) from specific force ``acc`` (..., 3), the device assumed still.

    With f = acc, the Z-Y-X attitude (see ``magnet.frames``) gives f = g (sin p, -sin r cos p, -cos r cos p), so

        pitch = atan2(f_x, sqrt(f_y^2 + f_z^2))   in [-90, 90]
        roll  = atan2(-f_y, -f_z)                 in (-180, 180]
    """
    f = np.asarray(acc, dtype=float)
    pitch = np.degrees(np.arctan2(f[..., 0], np.hypot(f[..., 1], f[..., 2])))
    roll = np.degrees(np.arctan2(-f[..., 1], -f[..., 2]))
    return pitch, np.where(roll <= -180.0, 180.0, roll)


def level_heading_deg(field: np.ndarray) -> np.ndarray:
    """Magnetic heading of a level device from the field (..., 3) in the body frame (seed 001 eqs. 2-5).

    A level device at heading h sees the horizontal field H as (H cos h, -H sin h) on its x (forward) and y (right)
    axes, so h = atan2(-B_y, B_x), quadrant-correct, in [0, 360).
    """
    b = np.asarray(field, dtype=float)
    return wrap_deg(np.degrees(np.arctan2(-b[..., 1], b[..., 0])))


def row_norm(v: np.ndarray) -> np.ndarray:
    """|v| of vectors (..., 3), component by component (several times faster than ``np.linalg.norm(axis=-1)`` on
    (S, 3) arrays)."""
    return np.sqrt(v[..., 0] * v[..., 0] + v[..., 1] * v[..., 1] + v[..., 2] * v[..., 2])


def rows_finite(v: np.ndarray) -> np.ndarray:
    """(...,) bool: every component of the vectors (..., k) is finite (faster than ``.all(axis=-1)`` for small k)."""
    finite = np.isfinite(v)
    out = finite[..., 0].copy()
    for k in range(1, v.shape[-1]):
        out &= finite[..., k]
    return out


def _down(acc: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The unit down direction -acc / |acc| as three component arrays (...,), NaN where |acc| is tiny."""
    f = np.asarray(acc, dtype=float)
    norm = row_norm(f)
    with np.errstate(invalid="ignore", divide="ignore"):
        scale = np.where(norm > _TINY, -1.0 / norm, np.nan)
    return f[..., 0] * scale, f[..., 1] * scale, f[..., 2] * scale


def _horizontal_frame(field: np.ndarray, acc: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """down (unit), east and north (both of length |B_horizontal|) in body coordinates, each (..., 3)."""
    b = np.asarray(field, dtype=float)
    dx, dy, dz = _down(acc)
    bx, by, bz = b[..., 0], b[..., 1], b[..., 2]
    ex, ey, ez = dy * bz - dz * by, dz * bx - dx * bz, dx * by - dy * bx  # east = down x B
    north = np.stack([ey * dz - ez * dy, ez * dx - ex * dz, ex * dy - ey * dx], axis=-1)  # east x down
    return np.stack([dx, dy, dz], axis=-1), np.stack([ex, ey, ez], axis=-1), north


def tilt_compensated_heading_deg(field: np.ndarray, acc: np.ndarray) -> np.ndarray:
    """Magnetic heading (degrees, [0, 360)) of a tilted device from the field (..., 3) and specific force (..., 3).

    Cross-product form (no Euler angles, so no singularity short of the x axis pointing straight up or down):
    with d = -acc / |acc| the down direction in body axes,

        e = d x B   (east, horizontal, |e| = |B_horizontal|)
        n = e x d   (north, horizontal, same length)
        heading = atan2(e_x, n_x)

    since the body x axis has components (cos h cos p) on north and (sin h cos p) on east. Samples with a zero
    accelerometer reading give NaN.
    """
    return _tilt_kernel(field, acc, dip=False)  # compiled: east = down x B, north_x = (east x down)_x, sample by sample


def _tilt_kernel(field: np.ndarray, acc: np.ndarray, dip: bool) -> np.ndarray:
    """``magnet._kernels.tilt_heading`` over the broadcast vectors (..., 3): the heading, or with ``dip`` the dip."""
    b, f = np.broadcast_arrays(np.asarray(field, dtype=float), np.asarray(acc, dtype=float))
    out = np.empty(b.shape[:-1])
    flat = out.reshape(-1)
    _kernels.tilt_heading(b.reshape(-1, 3), f.reshape(-1, 3), None if dip else flat, flat if dip else None)
    return out


def heading_uncertainty_deg(field: np.ndarray, acc: np.ndarray, field_error_ut: float) -> np.ndarray:
    """One-sigma heading uncertainty (degrees) from a field error ``field_error_ut`` (uT, e.g. the calibration's
    residual RMS) and the horizontal field the device sees: atan(error / |B_horizontal|); 180 where there is no
    horizontal field."""
    _, east, _ = _horizontal_frame(field, acc)
    horizontal = np.linalg.norm(east, axis=-1)
    with np.errstate(divide="ignore", invalid="ignore"):
        sigma = np.degrees(np.arctan2(float(field_error_ut), horizontal))
    return np.where(horizontal > _TINY, sigma, 180.0)


def true_heading_deg(magnetic_deg: npt.ArrayLike, declination_deg: npt.ArrayLike) -> np.ndarray:
    """True heading = magnetic heading + declination (east positive), wrapped to [0, 360)."""
    return wrap_deg(np.asarray(magnetic_deg, dtype=float) + np.asarray(declination_deg, dtype=float))


def smooth_heading_deg(heading_deg: np.ndarray, window: int) -> np.ndarray:
    """Trailing sliding-window circular mean (seed 004's sliding window, done on the circle).

    Output i is the direction of the sum of unit vectors of headings i-window+1 .. i (fewer at the start), so 359 and
    1 average to 0, never 180. heading (N,) in degrees -> (N,) in [0, 360). ``window`` >= 1 samples.
    """
    if isinstance(window, bool) or not isinstance(window, (int, np.integer)) or window < 1:
        raise ValueError(f"smoothing window must be a whole number of samples >= 1, got {window!r}")
    h = np.radians(np.asarray(heading_deg, dtype=float))
    if h.ndim != 1:
        raise ValueError(f"headings must be a 1-D array, got shape {h.shape}")
    sums = []
    for part in (np.cos(h), np.sin(h)):
        cumulative = np.concatenate([[0.0], np.cumsum(part)])
        upper = np.arange(1, h.size + 1)
        sums.append(cumulative[upper] - cumulative[np.maximum(upper - window, 0)])
    return wrap_deg(np.degrees(np.arctan2(sums[1], sums[0])))


def dip_angle_deg(field: np.ndarray, acc: np.ndarray) -> np.ndarray:
    """Dip of the field below the horizon, degrees in [-90, 90]: asin(B . d / |B|) with d = -acc / |acc| (down).

    It equals the local inclination whatever the attitude, so it checks both calibration and disturbance.
    """
    return _tilt_kernel(field, acc, dip=True)  # compiled, sample by sample


#: with no calibration in force, a field further than this from the expected strength (%) is no Earth field: a raw
#: phone magnetometer carries hard iron of 6-15 times the Earth's field, and a filter fed that field turns its heading
#: with every tilt and turn (39 deg RMS on walks); without it the filter holds its heading on the gyroscope
NO_EARTH_FIELD_PCT = 30.0


def no_earth_field(field_ut: np.ndarray, expected_ut: npt.ArrayLike | None) -> np.ndarray:
    """(...) bool: the fields (..., 3) uT no Earth field can be: |B| more than NO_EARTH_FIELD_PCT % from the expected
    strength where one is known (``expected_ut``: one value or one per field, NaN or 0 where unknown), else outside
    the range the Earth's field has anywhere (EARTH_MIN_UT..EARTH_MAX_UT). The compass and ``magnet heading`` leave
    such samples out of the attitude filter while no calibration is in force."""
    norm = row_norm(np.asarray(field_ut, dtype=float))
    expected = np.asarray(np.nan if expected_ut is None else expected_ut, dtype=float)
    expected = expected if expected.shape == norm.shape else np.broadcast_to(expected, norm.shape)
    known = np.isfinite(expected) & (expected > 0)
    low = np.where(known, expected * (1.0 - NO_EARTH_FIELD_PCT / 100.0), EARTH_MIN_UT)
    high = np.where(known, expected * (1.0 + NO_EARTH_FIELD_PCT / 100.0), EARTH_MAX_UT)
    with np.errstate(invalid="ignore"):
        return (norm < low) | (norm > high)


def leave_out_no_earth_field(
    filter_field: np.ndarray,
    field_ut: np.ndarray,
    flags: np.ndarray,
    uncalibrated: np.ndarray,
    expected_ut: npt.ArrayLike | None,
) -> tuple[np.ndarray, np.ndarray]:
    """(the field (S, 3) the attitude filter gets, with zero rows where ``no_earth_field`` of the corrected
    ``field_ut`` (S, 3) and ``uncalibrated`` (S,) bool; ``flags`` (S,) int64 with those rows flagged FIELD_DISTURBED):
    no record, no Earth field, and the filter holds its heading on the gyroscope."""
    blind = uncalibrated & no_earth_field(field_ut, expected_ut)
    if not blind.any():
        return filter_field, flags
    return np.where(blind[:, None], 0.0, filter_field), flags | np.where(blind, int(HeadingFlag.FIELD_DISTURBED), 0)


def disturbance_flags(
    field: np.ndarray,
    acc: np.ndarray | None,
    expected_ut: npt.ArrayLike | None,
    expected_dip_deg: npt.ArrayLike | None,
    field_tol_pct: float = 15.0,
    dip_tol_deg: float = 5.0,
    dip_deg: np.ndarray | None = None,
) -> np.ndarray:
    """HeadingFlag bits (int64, shape (...)) for corrected fields (..., 3) in uT and specific force (..., 3) or None
    (the one disturbance check: the live compass, ``magnet heading`` and the tests all call it).

    ``expected_ut`` and ``expected_dip_deg``: one value or one per sample (...); None, NaN or (for the field) 0 where
    nothing is expected, which sets no bit. ``dip_deg`` (...): the dip already computed from field and acc, if so.
    FIELD_DISTURBED: | |B| - expected_ut | > field_tol_pct % of expected_ut.
    DIP_DISTURBED: |dip - expected_dip_deg| > dip_tol_deg, where there is a tilt.
    NO_TILT: acc is None, or a sample's acc is zero or not finite. CALIBRATED is the caller's to add.
    """
    b = np.asarray(field, dtype=float)
    shape = b.shape[:-1]
    f = None if acc is None else np.asarray(acc, dtype=float)
    f = f if f is None or f.shape == b.shape else np.broadcast_to(f, b.shape)
    dip = None
    if f is not None and expected_dip_deg is not None:
        dip = dip_angle_deg(b, f) if dip_deg is None else dip_deg
    flat = [None if x is None else _samples(x, shape) for x in (expected_ut, dip, expected_dip_deg)]
    flags = np.empty(shape, dtype=np.int64)
    _kernels.disturbance_bits(
        b.reshape(-1, 3), None if f is None else f.reshape(-1, 3), flat[0], flat[1], flat[2] if dip is not None
        else None, field_tol_pct, dip_tol_deg, _TINY, flags.reshape(-1),
    )  # fmt: skip
    return flags


def _samples(values: npt.ArrayLike, shape: tuple[int, ...]) -> np.ndarray:
    """``values`` broadcast to ``shape``, flat, float64 (a view where it can be)."""
    arr = np.asarray(values, dtype=float)
    return (arr if arr.shape == shape else np.broadcast_to(arr, shape)).reshape(-1)


def offset_removed_rms_deg(estimate_deg: np.ndarray, reference_deg: np.ndarray) -> float:
    """RMS (degrees) of estimate - reference after removing one constant offset, their circular mean difference.

    Both (N,) in degrees. The offset absorbs a reference whose north is arbitrary (an optical frame) or a constant
    declination. NaN when there are no samples.
    """
    diff = np.radians(angle_difference_deg(estimate_deg, reference_deg))
    if diff.size == 0:
        return math.nan
    offset = np.arctan2(np.sin(diff).mean(), np.cos(diff).mean())
    residual = np.mod(diff - offset + np.pi, 2 * np.pi) - np.pi
    return float(np.degrees(np.sqrt(np.mean(residual**2))))
