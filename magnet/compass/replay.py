"""A velocity-aided device's last seconds, kept so that a new record can be fused again over them.

A new record restarts a velocity-aided filter whole (``Fusion.restart_magnetometer``): its attitude was built on
the old correction, and before the first record its heading is anyone's, so the velocity's acceleration it turned
into the body bent its tilt too. Started again on the next batch alone, the new filter's first samples come before
it has an attitude to turn the acceleration with, and its tilt and heading take seconds to settle (the restart's
tail: docs/field-calibration.md, "A new record fused again"). So each aided device's filter keeps its last
``REPLAY_S`` of samples as it took them (time, velocity, gyroscope, accelerometer and the *raw* field, vqf's frames),
and a new record restarts the filter and feeds it those samples again, their field corrected by the new record:
by the next batch the filter has fused ``REPLAY_S`` with the record, as if it had been in force then. The outputs of
the samples fed again are not published again (they were answered when they came).

Bounded: ``REPLAY_S`` of samples (13 float64 each: 100 Hz, 10 s, about 100 kB) per aided device, none for others.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import NamedTuple

import numpy as np

from magnet.attitude.aided_fusion import carry_forward
from magnet.attitude.aiding import VelocityFixes
from magnet.attitude.fusion import Fusion
from magnet.attitude.mag_delay import advance_field
from magnet.frames import (
    frd_flu,
    quaternion_conjugate,
    quaternion_multiply,
    quaternion_to_matrix,
    rotation_vector_to_quaternion,
)
from magnet.model import Calibration
from magnet.units import STANDARD_GRAVITY_MS2

#: seconds of an aided device's samples fed again to its filter with a new record
REPLAY_S = 10.0
#: a row: time (s), velocity (3, magnetic NED m/s, NaN where unknown), gyroscope, accelerometer, raw field (vqf frame)
ROW_SIZE = 13
#: seconds of samples the attitude the filter starts again from is worked out over (``start_attitude``)
AVERAGE_S = 0.2
#: the recent samples are fed again only where the vehicle's horizontal acceleration reached this (m/s^2; see
#: ``start_attitude``); below it a record restarts the filter on the next batch, the velocity's fixes kept
REPLAY_ACCELERATION_MS2 = 2.0

#: the raw field (N, 3) and the gyroscope (N, 3), vqf's frame, -> the field (N, 3) the filter gets, vqf's frame
Corrector = Callable[[np.ndarray, np.ndarray], np.ndarray]


class RecentSamples:
    """The last ``seconds`` of a device's samples at ``period_s``: a buffer of twice the capacity, its newest rows
    moved back to the start when it fills (one copy every capacity rows, none per sample)."""

    def __init__(self, period_s: float, seconds: float = REPLAY_S) -> None:
        if not (period_s > 0 and seconds > 0):
            raise ValueError(f"period_s and seconds must be > 0, got {period_s!r} and {seconds!r}")
        self.period_s = period_s
        self.capacity = max(round(seconds / period_s), 1)
        self._rows = np.empty((2 * self.capacity, ROW_SIZE))
        self._start = self._count = 0

    def __len__(self) -> int:
        return self._count

    def clear(self) -> None:
        self._start = self._count = 0

    def add(self, t_s: np.ndarray, vel: np.ndarray, gyr: np.ndarray, acc: np.ndarray, raw: np.ndarray) -> None:
        """Samples' times (N,) s, velocities (N, 3) and gyroscope, accelerometer and raw field (N, 3), in order."""
        count = len(t_s)
        if count >= self.capacity:
            take = slice(count - self.capacity, count)
            t_s, vel, gyr, acc, raw = t_s[take], vel[take], gyr[take], acc[take], raw[take]
            self._start = self._count = 0
            count = self.capacity
        end = self._start + self._count
        if end + count > len(self._rows):  # keep the newest rows that stay, at the start
            keep = min(self._count, self.capacity - count)
            self._rows[:keep] = self._rows[end - keep : end]
            self._start, self._count, end = 0, keep, keep
        rows = self._rows[end : end + count]
        rows[:, 0], rows[:, 1:4], rows[:, 4:7], rows[:, 7:10], rows[:, 10:13] = t_s, vel, gyr, acc, raw
        self._count += count
        if self._count > self.capacity:
            self._start += self._count - self.capacity
            self._count = self.capacity

    def columns(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Times (n,), velocities, gyroscope, accelerometer, raw field (n, 3): C-contiguous copies, oldest first."""
        rows = self._rows[self._start : self._start + self._count]
        vel, gyr, acc, raw = (np.ascontiguousarray(rows[:, a : a + 3]) for a in (1, 4, 7, 10))
        return rows[:, 0].copy(), vel, gyr, acc, raw


def kept(
    recent: RecentSamples | None, period_s: float, t_s: np.ndarray, vel: np.ndarray, *vectors: np.ndarray
) -> RecentSamples:
    """``recent`` (a new one where None or of another period) with samples added (``RecentSamples.add``)."""
    if recent is None or recent.period_s != period_s:
        recent = RecentSamples(period_s)
    recent.add(t_s, vel, *vectors)
    return recent


def fuse_again(fusion: Fusion, recent: RecentSamples | None, correct: Corrector | None) -> bool:
    """Restart an aided ``fusion`` from the attitude its ``recent`` samples give (``start_attitude``) and feed them
    again, their raw field corrected by ``correct``; False (nothing done) where it is not aided, no samples or no
    correction are there, or ``start_attitude`` gives none."""
    if correct is None or recent is None or not len(recent) or not fusion.aided:
        return False
    again = recent.columns()
    start = start_attitude(*again[:4], correct(again[4], again[2]))
    if start is None:
        return False
    t_s, vel, gyr, acc, raw = (x[start.first :] for x in again)
    fusion.restart_magnetometer(keep_fixes=False, quat_vqf=start.quat_vqf)  # the samples bring their fixes again
    fusion.update_vqf_frame(gyr, acc, correct(raw, gyr), t_s, vel)
    return True


def corrector(calibration: Calibration) -> Corrector | None:
    """How the compass corrects the field its filter gets (``Correction.apply``: B = A (u - b), turned forward over
    the record's magnetometer lag), for samples in vqf's frame; None for a record with a motor model (the motors'
    field needs each batch's current or throttle, which are not kept: such a filter starts again on the next batch)."""
    if calibration.motor is not None:
        return None
    matrix, offset, lag_s = calibration.matrix, calibration.offset, calibration.mag_lag_s

    def correct(raw_vqf: np.ndarray, gyr_vqf: np.ndarray) -> np.ndarray:
        field = (frd_flu(raw_vqf) - offset) @ matrix.T
        if lag_s:
            field = advance_field(field, frd_flu(gyr_vqf), lag_s)
        return np.ascontiguousarray(frd_flu(field))

    return correct


class Start(NamedTuple):
    """Where recent samples are fed again from (``first``, an index) and the attitude there (``quat_vqf`` (4,),
    vqf's quaternion body -> ENU with magnetic north)."""

    first: int
    quat_vqf: np.ndarray


def start_attitude(
    t_s: np.ndarray, vel: np.ndarray, gyr: np.ndarray, acc: np.ndarray, field: np.ndarray
) -> Start | None:
    """Where to feed recent samples again from, and the attitude there; None where the velocity's acceleration is
    known nowhere, or stayed under ``REPLAY_ACCELERATION_MS2`` (the restart is left as it was).

    A new filter takes its first tilt from the accelerometer, which in a vehicle reads its acceleration too; that
    tilt turns the field's heading (by the tilt times tan(dip)), and that heading turns the velocity's acceleration
    into the body the wrong way: at a dip of 67 deg and 5 m/s^2 the two feed each other (a heading error comes back
    1.2 times larger), and the filter stays 6-12 deg off in tilt for seconds. Here the attitude comes from two
    vectors known in both frames at once: the specific force (the velocity's acceleration less gravity, ENU) against
    the accelerometer, and magnetic north (the field's east component zero) against the corrected field: the turn
    that maps the one, about it the angle that puts the field in the north-up plane. Samples: times (n,) s, held
    velocities (n, 3) m/s magnetic NED (NaN where unknown), gyroscope, accelerometer and corrected field (n, 3), vqf
    frames; from the first new fix on (a held velocity's own time is unknown), averaged over ``AVERAGE_S``, and
    turned back to the first fix's sample by the gyroscope. Samples at least 3."""
    if len(t_s) < 3:
        return None
    period_s = float(np.median(np.diff(t_s)))
    moved = np.flatnonzero(np.isfinite(vel[1:, 0]) & np.any(vel[1:] != vel[:-1], axis=1))
    if not moved.size:
        return None
    first = int(moved[0]) + 1
    fixes = VelocityFixes(max_fixes=len(t_s) + 2)
    fixes.observe(t_s[first:], vel[first:])
    if len(fixes.times_s) < 2:
        return None
    known = np.flatnonzero((t_s >= fixes.times_s[0] + fixes.half_window_s) & (t_s <= fixes.known_until_s))
    if not known.size or np.linalg.norm(fixes.acceleration(t_s[known])[:, :2], axis=1).max() < REPLAY_ACCELERATION_MS2:
        return None
    rows = known[: max(round(AVERAGE_S / period_s), 1)]
    if rows[-1] - rows[0] != len(rows) - 1:
        return None
    a_ned = fixes.acceleration(t_s[rows]).mean(axis=0)
    force_enu = np.array([a_ned[1], a_ned[0], STANDARD_GRAVITY_MS2 - a_ned[2]])
    quat = _two_vector_attitude(acc[rows].mean(axis=0), force_enu, field[rows].mean(axis=0))
    back = carry_forward(np.array([1.0, 0.0, 0.0, 0.0]), gyr[first : rows[0]], np.zeros(3), period_s)
    if len(back):
        quat = quaternion_multiply(quat, quaternion_conjugate(back[-1]))
    return Start(first, quat)


def _two_vector_attitude(force_body: np.ndarray, force_enu: np.ndarray, field_body: np.ndarray) -> np.ndarray:
    """vqf's quaternion (4,) body -> ENU that maps ``force_body`` (3,) onto the direction of ``force_enu`` (3,) and
    puts ``field_body`` (3,) in the plane of up and north (east zero, north positive)."""
    u, v = force_enu / np.linalg.norm(force_enu), force_body / np.linalg.norm(force_body)
    axis = np.cross(v, u)
    angle = np.arctan2(np.linalg.norm(axis), float(v @ u))
    tilt = rotation_vector_to_quaternion(axis / max(np.linalg.norm(axis), 1e-12) * angle)
    b = quaternion_to_matrix(tilt) @ field_body
    along = u * float(u @ b)
    across, side = b - along, np.cross(u, b)
    # east of along + across cos(t) + side sin(t) is zero: r cos(t - phi) = -along_east
    r, phi = np.hypot(across[0], side[0]), np.arctan2(side[0], across[0])
    spread = np.arccos(np.clip(-along[0] / max(r, 1e-12), -1.0, 1.0))
    north = [along[1] + across[1] * np.cos(t) + side[1] * np.sin(t) for t in (phi + spread, phi - spread)]
    turn = phi + spread if north[0] >= north[1] else phi - spread
    return quaternion_multiply(rotation_vector_to_quaternion(u * turn), tilt)


def aiding_columns(order: np.ndarray | None, t_ns: np.ndarray, vel_ned_ms: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """An aided filter's times (S,) s (float64 keeps wall-clock seconds to a microsecond) and velocities (S, 3) for a
    drain of ``magnet.compass.filters``, permuted by its ``order`` (None: as they are)."""
    t_s = t_ns.astype(float) * 1e-9
    return (t_s, vel_ned_ms) if order is None else (t_s[order], vel_ned_ms[order])
