"""Autopilot conventions shared by the flight-log readers and the parameter export (see ``docs/autopilots.md``).

Both PX4 and ArduPilot express the field in the vehicle's body frame x forward, y right, z down (FRD), as magnet
does. ArduPilot keeps the field in milligauss, PX4 in gauss; magnet in uT (1 mGauss = 0.1 uT, 1 gauss = 100 uT).

The autopilots' sensor orientation parameters (ArduPilot ``COMPASS_ORIENTn``, PX4 ``CAL_MAGn_ROT`` and
``SENS_BOARD_ROT``) pick one rotation from a numbered table: ``magnet.frames.ROTATIONS``.

``ardupilot_raw_field`` undoes ArduPilot's correction of a logged ``MAG`` record, and ``align`` resamples another
sensor's stream at the magnetometer's sample times.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import numpy.typing as npt

from magnet.attitude.heading import angle_difference_deg

#: ArduPilot applies COMPASS_SCALE only inside this range (outside it, no scaling at all)
ARDUPILOT_SCALE_RANGE = (0.85, 1.4)


def ardupilot_soft_iron(diagonals: npt.ArrayLike, offdiagonals: npt.ArrayLike) -> np.ndarray:
    """ArduPilot's symmetric soft-iron matrix (3, 3) from COMPASS_DIA{X,Y,Z} and COMPASS_ODI{X,Y,Z}: diagonals on
    the diagonal, ODI_X at (0,1), ODI_Y at (0,2), ODI_Z at (1,2), mirrored; all-zero diagonals mean identity."""
    dia = np.asarray(diagonals, dtype=float)
    odi = np.asarray(offdiagonals, dtype=float)
    if not np.any(dia):
        dia = np.ones(3)
    return np.array([[dia[0], odi[0], odi[1]], [odi[0], dia[1], odi[2]], [odi[1], odi[2], dia[2]]])


def ardupilot_scale(scale: float) -> float:
    """The factor ArduPilot really applies for COMPASS_SCALE ``scale``: itself inside ARDUPILOT_SCALE_RANGE, else 1."""
    low, high = ARDUPILOT_SCALE_RANGE
    return float(scale) if low <= scale <= high else 1.0


def ardupilot_raw_field(
    field_mg: np.ndarray,
    offsets_mg: np.ndarray,
    motor_offsets_mg: np.ndarray,
    soft_iron: np.ndarray,
    scale: float = 0.0,
) -> np.ndarray:
    """The body-frame field before ArduPilot's correction, (N, 3) milligauss, from logged ``MAG`` records.

    ArduPilot corrects a reading r (body frame, mGauss) as ``W (s (r + o)) + m``: o the offsets (OfsX..Z), s the
    scale factor (``ardupilot_scale``), W the soft-iron matrix, m the motor offsets (MOfsX..Z); the record's MagX..Z
    is the result. This inverts it: r = W^-1 (field - m) / s - o. field_mg, offsets_mg, motor_offsets_mg: (N, 3)
    (or (3,)) mGauss; soft_iron (3, 3)."""
    s = ardupilot_scale(scale)
    unmoved = np.asarray(field_mg, dtype=float) - np.asarray(motor_offsets_mg, dtype=float)
    return np.linalg.solve(soft_iron, unmoved.T).T / s - np.asarray(offsets_mg, dtype=float)


def align(t_to: np.ndarray, t_from: np.ndarray, values: np.ndarray) -> np.ndarray:
    """``values`` (M,) or (M, K) sampled at ``t_from`` (M,), linearly interpolated at ``t_to`` (N,): (N,) or (N, K).
    Times in any one unit, ``t_from`` increasing; outside its span the nearest end value is held."""
    values = np.asarray(values, dtype=float)
    if values.ndim == 1:
        return np.interp(t_to, t_from, values)
    return np.column_stack([np.interp(t_to, t_from, values[:, k]) for k in range(values.shape[1])])


def align_angle_deg(t_to: np.ndarray, t_from: np.ndarray, angle_deg: np.ndarray) -> np.ndarray:
    """Angles in degrees (M,) at ``t_from`` interpolated along the short way round at ``t_to``: (N,) in [0, 360)."""
    unwrapped = np.degrees(np.unwrap(np.radians(np.asarray(angle_deg, dtype=float))))
    return np.mod(np.interp(t_to, t_from, unwrapped), 360.0)


def increasing(t: np.ndarray) -> np.ndarray:
    """Boolean mask (N,) keeping the samples whose time is later than every one before (drops repeats and steps
    back, as a log's restarted or duplicated records give)."""
    t = np.asarray(t, dtype=float)
    if t.size == 0:
        return np.zeros(0, dtype=bool)
    before = np.maximum.accumulate(np.concatenate(([-np.inf], t[:-1])))
    return t > before


@dataclasses.dataclass(frozen=True)
class HeadingComparison:
    """Headings against an autopilot's own: rms_deg and max_deg of the difference after removing offset_deg (their
    circular mean difference, degrees), over count samples inside the reference's time span."""

    rms_deg: float
    offset_deg: float
    max_deg: float
    count: int


def compare_headings(
    t_s: np.ndarray, heading_deg: np.ndarray, reference_t_s: np.ndarray, reference_deg: np.ndarray
) -> HeadingComparison:
    """Compare headings (N,) at times t_s (N,) with a reference (M,) at reference_t_s (M,), increasing, same clock;
    the reference is interpolated (the short way round) at each sample inside its span. ValueError when no sample
    falls inside it."""
    t = np.asarray(t_s, dtype=float)
    inside = (t >= reference_t_s[0]) & (t <= reference_t_s[-1]) & np.isfinite(heading_deg)
    if len(reference_t_s) < 2 or not inside.any():
        raise ValueError("the autopilot's attitude and the magnetometer samples do not overlap in time")
    reference = align_angle_deg(t[inside], reference_t_s, reference_deg)
    diff = np.radians(angle_difference_deg(np.asarray(heading_deg)[inside], reference))
    offset = float(np.arctan2(np.sin(diff).mean(), np.cos(diff).mean()))
    residual = np.degrees(np.mod(diff - offset + np.pi, 2 * np.pi) - np.pi)
    rms = float(np.sqrt(np.mean(residual**2)))
    return HeadingComparison(rms, float(np.degrees(offset)), float(np.abs(residual).max()), int(inside.sum()))
