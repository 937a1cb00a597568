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

import numpy as np

from magnet.calibration.base import FitError
from magnet.frames import rotation_vector_to_matrix

#: samples per window of the integrated constraint
WINDOW = 10
#: the least singular value must be this far below the next one: the solution is one direction, not a plane
NULL_RATIO = 0.05


def constraint_rows(mag: np.ndarray, gyr_rads: np.ndarray, period_s: float, window: int = WINDOW) -> np.ndarray:
    """The linear constraints (3 W, 12) on x = (A row by row, c), one block of 3 per window of ``window`` samples:
    A m(s + W) - c = P^T (A m(s) - c), P the product of the window's turns (the rate of sample k + 1 carries the
    attitude from sample k to k + 1), so b(s + W) = P^T b(s) exactly for a constant earth field."""
    count = (len(mag) - 1) // window
    if count < 4:
        raise FitError(f"gyro-ellipsoid needs at least {4 * window + 1} samples with the gyroscope, got {len(mag)}")
    turns = rotation_vector_to_matrix(np.asarray(gyr_rads, dtype=float) * period_s)  # exp([w_k dt]x)
    starts = np.arange(count) * window
    product = np.broadcast_to(np.eye(3), (count, 3, 3)).copy()
    for step in range(window):
        product = product @ turns[starts + step + 1]
    back = np.transpose(product, (0, 2, 1))  # P^T
    ahead = np.einsum("il,nj->nilj", np.eye(3), mag[starts + window]).reshape(count, 3, 9)
    behind = np.einsum("nil,nj->nilj", back, mag[starts]).reshape(count, 3, 9)
    return np.concatenate([ahead - behind, back - np.eye(3)], axis=2).reshape(3 * count, 12)


def fit_gyro_ellipsoid(
    mag: np.ndarray, gyr_rads: np.ndarray, period_s: float, field_ut: float | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """(offset (3,), matrix A (3, 3)) with b = A (m - offset) from raw field mag (N, 3) and body rates gyr (N, 3)
    rad/s sampled every ``period_s`` seconds (the rate of a sample is over the period ending at it). ``field_ut``
    the field strength to scale to (None: the raw median |m|). FitError when the rotation cannot determine it."""
    mag, gyr = np.asarray(mag, dtype=float), np.asarray(gyr_rads, dtype=float)
    if mag.shape != gyr.shape or mag.ndim != 2 or mag.shape[1] != 3:
        raise FitError(f"gyro-ellipsoid needs mag and gyr of the same shape (N, 3), got {mag.shape} and {gyr.shape}")
    centre = np.median(mag, axis=0)
    spread = float(np.median(np.linalg.norm(mag - centre, axis=1))) or 1.0
    rows = constraint_rows((mag - centre) / spread, gyr, period_s)
    _, singular, vt = np.linalg.svd(rows.T @ rows)
    if singular[-2] < 1e-9 * singular[0] or singular[-1] > NULL_RATIO * singular[-2]:
        raise FitError(
            "gyro-ellipsoid: the rotation does not determine the calibration (turn the device about every axis)"
        )
    matrix, c = vt[-1][:9].reshape(3, 3), vt[-1][9:]
    if np.linalg.det(matrix) < 0:
        matrix, c = -matrix, -c
    offset_scaled = np.linalg.solve(matrix, c)
    field = ((mag - centre) / spread - offset_scaled) @ matrix.T
    target = float(field_ut) if field_ut else float(np.median(np.linalg.norm(mag, axis=1)))
    scale = target / float(np.median(np.linalg.norm(field, axis=1)))
    return centre + spread * offset_scaled, matrix * scale / spread
