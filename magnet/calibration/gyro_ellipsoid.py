"""Magnetometer calibration from the gyroscope: offset, soft iron and the magnetometer-to-IMU rotation at once.

Design: docs/design.md, "Heading in motion" (calibration that uses the gyroscope). The idea is that of Kok and Schon
(IEEE Sensors Journal, 2016): in a constant earth field, the field seen in the body frame turns only because the body
turns, so the calibrated field must obey db/dt = -w x b, w the body rate the gyroscope measures (in the IMU's frame).
With b = A (m - o), A a general 3x3 matrix (soft iron, scale and the rotation of the magnetometer's axes into the
IMU's), and over a short window from sample s to s + W, P the rotation the gyroscope measures over it (the
product of each sample's turn exp([w dt]x)) and c = A o:

    A m(s + W) - c = P^T (A m(s) - c)

which is linear and homogeneous in the twelve unknowns (A, c). A window of several samples instead of one keeps
the field's change large beside the magnetometer's noise. The stacked windows are solved by the singular
vector of least singular value (total least squares); the scale, which the gyroscope cannot see, is set so that the
median |b| is the field strength asked for (the WMM's, or the raw median); the sign so that det A > 0. The rotation
is what an ellipsoid fit cannot give: it is observable here because the gyroscope's axes are the reference.

Needs rotation about at least two axes (a level turn leaves the axis it turns about unconstrained), and a gyroscope
bias adds an error of about bias / rate: judge the result with the gate like any other fit. Pure numpy.
"""

from __future__ import annotations

import contextlib
import math

import numpy as np

from magnet.calibration.base import FitError, Shape
from magnet.frames import rotation_vector_to_matrix

#: a window ends once the gyroscope has turned this far since its start (the field's change then stands well above
#: the magnetometer's noise) ...
WINDOW_ANGLE_DEG = 45.0
#: ... or after this long, the longest a gyroscope bias is integrated over (s)
MAX_WINDOW_S = 1.0
#: windows that turned less than this are left out (they carry mostly noise)
MIN_WINDOW_ANGLE_DEG = 10.0
#: at most this many windows (starts spread evenly); more add time, not information
MAX_WINDOWS = 20_000
#: the magnetometer's readings may come this much later (or earlier) than the gyroscope's: a chip's output filter
#: and sampling, or two chips read at different moments, delay one by a few to tens of ms (s)
MAX_LAG_S = 0.03
#: the least eigenvalue must be this far below the next one: the solution is one direction, not a plane
NULL_RATIO = 0.05


def gyro_attitudes(turns: np.ndarray) -> np.ndarray:
    """Rotations (N, 3, 3) Q_k = turns_1 turns_2 ... turns_k (Q_0 = I): sample k's axes in sample 0's, by a
    prefix product taken in log2(N) batched steps."""
    out = turns.copy()
    out[0] = np.eye(3)
    shift = 1
    while shift < len(out):
        out[shift:] = out[:-shift] @ out[shift:]
        shift *= 2
    return out


def skew(w: np.ndarray) -> np.ndarray:
    """[w]x (M, 3, 3) of vectors w (M, 3)."""
    out = np.zeros((len(w), 3, 3))
    out[:, 0, 1], out[:, 0, 2], out[:, 1, 2] = -w[:, 2], w[:, 1], -w[:, 0]
    out[:, 1, 0], out[:, 2, 0], out[:, 2, 1] = w[:, 2], -w[:, 1], w[:, 0]
    return out


def windows(
    gyr_rads: np.ndarray,
    period_s: float,
    angle_deg: float = WINDOW_ANGLE_DEG,
    longest_s: float = MAX_WINDOW_S,
    least_deg: float = MIN_WINDOW_ANGLE_DEG,
    every: int | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """(starts (M,), ends (M,)) sample indices: each window ends where the gyroscope has turned ``angle_deg`` (summed
    rate) or ``longest_s`` after its start; kept only when it turned at least ``least_deg``; a window starts at every
    ``every``-th sample (None: as many as ``MAX_WINDOWS`` allows)."""
    turned = np.concatenate([[0.0], np.cumsum(np.linalg.norm(gyr_rads[1:], axis=1) * period_s)])
    count = len(turned)
    starts = np.arange(0, count - 1, max(1, count // MAX_WINDOWS) if every is None else every)
    ends = np.searchsorted(turned, turned[starts] + np.radians(angle_deg))
    ends = np.minimum(np.minimum(ends, starts + max(1, round(longest_s / period_s))), count - 1)
    good = (ends > starts) & (turned[ends] - turned[starts] >= np.radians(least_deg))
    return starts[good], ends[good]


def kept_windows(
    starts: np.ndarray, ends: np.ndarray, keep: np.ndarray | None, most: int
) -> tuple[np.ndarray, np.ndarray]:
    """The windows (starts (M,), ends (M,)) whose both ends are in ``keep`` (N,) bool (None: all), at most ``most``
    of them (spread evenly)."""
    if keep is not None:
        both = keep[starts] & keep[ends]
        starts, ends = starts[both], ends[both]
    if len(starts) > most:
        pick = np.linspace(0, len(starts) - 1, most).astype(int)
        starts, ends = starts[pick], ends[pick]
    return starts, ends


def constraint_rows(
    mag: np.ndarray, attitudes: np.ndarray, starts: np.ndarray, ends: np.ndarray, lag: int = 0
) -> np.ndarray:
    """The linear constraints (3 M, 12) on x = (A row by row, c), one block of 3 per window s .. e:
    A m(e + lag) - c = P^T (A m(s + lag) - c), P = Q_s^T Q_e the turn the gyroscope measured over it
    (``gyro_attitudes``), so that b(e) = P^T b(s) exactly for a constant earth field; ``lag`` samples: how far the
    magnetometer's readings come behind the gyroscope's."""
    count = len(starts)
    if count < 12:
        raise FitError(
            f"gyro-ellipsoid found {count} stretches where the device turned {MIN_WINDOW_ANGLE_DEG:g}-"
            f"{WINDOW_ANGLE_DEG:g} deg within {MAX_WINDOW_S:g} s: turn the device about every axis while recording"
        )
    back = np.transpose(attitudes[ends], (0, 2, 1)) @ attitudes[starts]  # P^T
    ahead = np.einsum("il,nj->nilj", np.eye(3), mag[ends + lag]).reshape(count, 3, 9)
    behind = np.einsum("nil,nj->nilj", back, mag[starts + lag]).reshape(count, 3, 9)
    return np.concatenate([ahead - behind, back - np.eye(3)], axis=2).reshape(3 * count, 12)


#: windows' (starts, ends); a solution (A, c, least eigenvalue ratio)
_Spans = tuple[np.ndarray, np.ndarray]
_Solution = tuple[np.ndarray, np.ndarray, float]


def _solve(rows: np.ndarray) -> _Solution:
    """(A (3, 3), c (3,), the least eigenvalue over the next) minimising |rows x| with |A| = 1: noise enters the A
    columns only (the magnetometer's; the gyroscope's is small beside it), so c is eliminated and A is the least
    eigenvector of the Schur complement, which the noise shifts by the same amount in every direction (no bias
    towards a small c, as a plain total least squares over all twelve would have). FitError for turns about one
    axis."""
    normal = rows.T @ rows
    maa, mac, mcc = normal[:9, :9], normal[:9, 9:], normal[9:, 9:]
    values_c = np.linalg.eigvalsh(mcc)
    if values_c[0] < 1e-9 * values_c[-1]:
        raise FitError("gyro-ellipsoid: the device turned about one axis only (turn the device about every axis)")
    eliminate = np.linalg.solve(mcc, mac.T)  # c = -eliminate a
    values, vectors = np.linalg.eigh(maa - mac @ eliminate)
    a = vectors[:, 0]
    return a.reshape(3, 3), -eliminate @ a, float(values[0] / values[1]) if values[1] > 0 else np.inf


def _fit_at(scaled: np.ndarray, attitudes: np.ndarray, spans: _Spans, used: np.ndarray, lag: int) -> _Solution:
    """``_solve`` for the windows whose lagged magnetometer samples exist and are used."""
    starts, ends = spans
    ok = (starts + lag >= 0) & (ends + lag < len(scaled))
    ok[ok] &= used[starts[ok] + lag] & used[ends[ok] + lag]
    return _solve(constraint_rows(scaled, attitudes, starts[ok], ends[ok], lag))


def _fit_between(
    scaled: np.ndarray, attitudes: np.ndarray, steps: np.ndarray, spans: _Spans, used: np.ndarray, lag: float
) -> _Solution:
    """``_fit_at`` for a lag between whole samples: the magnetometer's sample ceil(lag) later is paired with the
    attitude ceil(lag) - lag of a sample after the window's ends, the gyroscope's turn over the next sample (``steps``
    (N, 3), rad: rate x period) taken that far. The gyroscope is interpolated, not the magnetometer: a field averaged
    between two samples is less noisy and would fit better half-way whatever the lag."""
    whole = math.ceil(lag)
    part = whole - lag
    if part == 0:
        return _fit_at(scaled, attitudes, spans, used, whole)
    between = attitudes.copy()
    between[:-1] = attitudes[:-1] @ rotation_vector_to_matrix(part * steps[1:])
    starts, ends = spans
    inside = ends + 1 < len(scaled)  # the last sample has no turn after it
    return _fit_at(scaled, between, (starts[inside], ends[inside]), used, whole)


def _refined_lag(
    scaled: np.ndarray,
    attitudes: np.ndarray,
    steps: np.ndarray,
    spans: _Spans,
    used: np.ndarray,
    best: tuple[int, _Solution],
    most: int,
) -> tuple[float, _Solution]:
    """The best whole lag refined between samples: the misfits at half and one sample either side, the parabola
    through them, and the fit at its vertex (within +-``most`` samples) when it fits better than the whole lag's (the
    points beside are the parabola's support, not candidates: the least of many noisy misfits would pick a lag by
    chance). At 50 Hz a sample is 20 ms, and a magnetometer 8-16 ms late (BROAD's 10-16 ms) is otherwise taken as none
    or 20 ms, the record then turning the field by the wrong angle in every fast turn (docs/field-calibration.md, "The
    already calibrated wand")."""
    centre = float(best[0])
    misfits = {centre: best[1][2]}
    for lag in (centre - 1.0, centre - 0.5, centre + 0.5, centre + 1.0):
        if abs(lag) > most:
            continue
        with contextlib.suppress(FitError):  # windows pushed out of the samples
            misfits[lag] = _fit_between(scaled, attitudes, steps, spans, used, lag)[2]
    if len(misfits) < 3:
        return best
    lags = np.array(sorted(misfits))
    curve = np.polyfit(lags - centre, [misfits[lag] for lag in lags], 2)
    if curve[0] <= 0:
        return best
    vertex = float(np.clip(centre - curve[1] / (2.0 * curve[0]), max(centre - 1.0, -most), min(centre + 1.0, most)))
    try:
        refined = _fit_between(scaled, attitudes, steps, spans, used, vertex)
    except FitError:
        return best
    return (vertex, refined) if refined[2] < best[1][2] else best


def _best_lag(
    scaled: np.ndarray, attitudes: np.ndarray, spans: _Spans, used: np.ndarray, most: int
) -> tuple[int, _Solution]:
    """(lag, its ``_solve``): the lag within +-``most`` samples whose misfit (least eigenvalue ratio) is least, the
    smaller lag on a tie. Every lag is tried: on a slow recording the misfit is not monotone in the lag, and a walk
    from none that stops where it first rises can stop at none (BROAD trial 05: none instead of 14 ms, and the
    record then made heading worse: docs/broad-motion.md)."""
    best = (0, _fit_at(scaled, attitudes, spans, used, 0))
    for lag in (lag for step in range(1, most + 1) for lag in (step, -step)):
        try:
            trial = _fit_at(scaled, attitudes, spans, used, lag)
        except FitError:  # the windows at the ends that a lag pushes out of the samples
            continue
        if trial[2] < best[1][2]:
            best = (lag, trial)
    return best


def gyro_ellipsoid(mag: np.ndarray, gyr_rads: np.ndarray, period_s: float, keep: np.ndarray | None = None) -> Shape:
    """The shape (offset (3,), matrix S (3, 3) with det S = 1, radius: the median |S (m - offset)|, raw unit) from
    raw field mag (N, 3) and body rates gyr (N, 3) rad/s sampled every ``period_s`` seconds (the rate of a sample is
    over the period ending at it), consecutive samples; ``keep`` (N,) bool: compare only kept magnetometer samples
    (None: all). S includes the rotation of the magnetometer's axes into the gyroscope's. The magnetometer's delay
    behind the gyroscope (within MAX_LAG_S: the whole samples, then refined between them) is the one that fits best;
    the note names it. FitError when the rotation cannot determine the calibration."""
    mag, gyr = np.asarray(mag, dtype=float), np.asarray(gyr_rads, dtype=float)
    if mag.shape != gyr.shape or mag.ndim != 2 or mag.shape[1] != 3:
        raise FitError(f"gyro-ellipsoid needs mag and gyr of the same shape (N, 3), got {mag.shape} and {gyr.shape}")
    used = np.ones(len(mag), dtype=bool) if keep is None else np.asarray(keep, dtype=bool)
    centre = np.median(mag[used], axis=0)
    spread = float(np.median(np.linalg.norm(mag[used] - centre, axis=1))) or 1.0
    steps = np.asarray(gyr, dtype=float) * period_s
    attitudes, spans = gyro_attitudes(rotation_vector_to_matrix(steps)), windows(gyr, period_s)
    scaled = (mag - centre) / spread
    most = round(MAX_LAG_S / period_s)
    found = _best_lag(scaled, attitudes, spans, used, most)
    lag, (matrix, c, ratio) = _refined_lag(scaled, attitudes, steps, spans, used, found, most)
    if ratio > NULL_RATIO:
        raise FitError(
            "gyro-ellipsoid: the rotation does not determine the calibration (turn the device about every axis)"
        )
    if np.linalg.det(matrix) < 0:
        matrix, c = -matrix, -c
    offset = centre + spread * np.linalg.solve(matrix, c)
    unit = matrix / np.cbrt(np.linalg.det(matrix))
    radius = float(np.median(np.linalg.norm((mag[used] - offset) @ unit.T, axis=1)))
    note = f"magnetometer {1e3 * lag * period_s:+.0f} ms behind the gyroscope" if lag else ""
    return Shape(offset, unit, radius, note, lag * period_s)
