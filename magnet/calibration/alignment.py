"""The ``ellipsoid+align`` method: the ellipsoid, then the rotation between magnetometer and accelerometer.

- ``ellipsoid+align``: the ellipsoid, then the rotation R between the magnetometer and accelerometer frames so that
  the dip is constant: with g_i the gravity directions (-acc normalised) and m_i the corrected field directions,
  g_i . (R m_i) = sin(dip) for every i. Start: linear least squares for N with g_i^T N m_i = 1, R0 = nearest
  rotation (SVD) to +-N; then Gauss-Newton on (rotation vector w, constant k): R <- R exp([w]x), residual
  g_i . (R m_i) - k, Jacobian row (m_i x R^T g_i, -1). A becomes R S. When the gravity directions do not span the
  sphere (smallest eigenvalue of their scatter < ``MIN_GRAVITY_SPREAD``) or the Jacobian is ill-conditioned, R = I
  and the note says alignment was not observable.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from magnet.calibration.base import FitError, Shape
from magnet.calibration.ellipsoid import ellipsoid
from magnet.frames import rotation_angle_deg, rotation_vector_to_matrix

#: smallest eigenvalue of the scatter of gravity directions (1/3 for the whole sphere) below which R is unobservable
MIN_GRAVITY_SPREAD = 0.02
#: largest condition number of the alignment Gauss-Newton normal matrix
MAX_ALIGN_CONDITION = 1e6


def ellipsoid_align(mag: np.ndarray, acc: np.ndarray | None, robust: bool) -> Shape:
    """The ellipsoid of mag (N, 3) (see ``ellipsoid``), then the rotation of the module docstring (acc (N, 3))."""
    return aligned(ellipsoid(mag, needs_acc(acc), robust), mag, acc)


def needs_acc(acc: np.ndarray | None) -> np.ndarray:
    """``acc``; FitError when there is none (the rotation is found against gravity)."""
    if acc is None:
        raise FitError("ellipsoid+align needs accelerometer samples (ax, ay, az) beside the field")
    return acc


def aligned(base: Shape, mag: np.ndarray, acc: np.ndarray | None) -> Shape:
    """``base`` (an ellipsoid of mag (N, 3)) turned by the rotation of the module docstring, found against the
    gravity of acc (N, 3); ``base`` with a note saying why when the rotation is not observable."""
    down = needs_acc(acc)
    gravity = -down / np.sqrt(np.einsum("ij,ij->i", down, down))[:, None]
    field = (mag - base.offset) @ base.matrix.T
    field /= np.sqrt(np.einsum("ij,ij->i", field, field))[:, None]
    rotation, why_not = align_rotation(field, gravity)
    if rotation is None:
        return dataclasses.replace(
            base, note=_join(base.note, f"alignment not observable: {why_not}; kept the plain ellipsoid")
        )
    angle = float(rotation_angle_deg(rotation))
    return dataclasses.replace(
        base,
        matrix=rotation @ base.matrix,
        note=_join(base.note, f"magnetometer-accelerometer misalignment {angle:.2f} deg corrected"),
    )


def _join(*notes: str) -> str:
    return "; ".join(note for note in notes if note)


def _gravity_spread(gravity: np.ndarray) -> float:
    return float(np.linalg.eigvalsh(gravity.T @ gravity / len(gravity))[0])


def align_rotation(
    field_dir: np.ndarray, gravity_dir: np.ndarray, iterations: int = 20
) -> tuple[np.ndarray | None, str]:
    """Rotation R (3,3) so that gravity_dir_i . (R field_dir_i) is the same for all i (both (N,3), unit rows).

    Returns (R, "") or (None, why it is not observable).
    """
    spread = _gravity_spread(gravity_dir)
    if spread < MIN_GRAVITY_SPREAD:
        return None, (
            f"gravity directions do not span the sphere (smallest spread {spread:.3f} < "
            f"{MIN_GRAVITY_SPREAD}); tilt and roll the device through all attitudes"
        )
    rotation = _initial_rotation(field_dir, gravity_dir)
    k = float(np.mean(np.einsum("ij,ij->i", gravity_dir, field_dir @ rotation.T)))
    for _ in range(iterations):
        rotated = field_dir @ rotation.T
        res = np.einsum("ij,ij->i", gravity_dir, rotated) - k
        normal, gradient = _normal_equations(field_dir, gravity_dir @ rotation, res)
        if np.linalg.cond(normal) > MAX_ALIGN_CONDITION:
            return None, "the rotation is ill-conditioned for these attitudes; tumble the device more widely"
        step = np.linalg.solve(normal, -gradient)
        rotation = rotation @ rotation_vector_to_matrix(step[:3])
        k += step[3]
        if np.linalg.norm(step[:3]) < 1e-10:
            break
    return rotation, ""


def _normal_equations(field_dir: np.ndarray, turned: np.ndarray, res: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(J^T J (4, 4), J^T res (4,)) of the Jacobian J = [m_i x (R^T g_i), -1] (N, 4), from its blocks: the cross
    products C (N, 3) give C^T C and C^T res, the constant column the sums (no (N, 4) array is built)."""
    m, t = field_dir, turned
    cross = np.empty((len(m), 3))
    cross[:, 0] = m[:, 1] * t[:, 2] - m[:, 2] * t[:, 1]
    cross[:, 1] = m[:, 2] * t[:, 0] - m[:, 0] * t[:, 2]
    cross[:, 2] = m[:, 0] * t[:, 1] - m[:, 1] * t[:, 0]
    total = cross.sum(axis=0)
    normal = np.empty((4, 4))
    normal[:3, :3] = cross.T @ cross
    normal[:3, 3] = normal[3, :3] = -total
    normal[3, 3] = len(res)
    return normal, np.append(cross.T @ res, -res.sum())


def _initial_rotation(field_dir: np.ndarray, gravity_dir: np.ndarray) -> np.ndarray:
    """Nearest rotation to N (or -N, the southern hemisphere) from the least squares g_i^T N m_i = 1."""
    design = np.einsum("ij,ik->ijk", gravity_dir, field_dir).reshape(len(field_dir), 9)
    n_vec, *_ = np.linalg.lstsq(design, np.ones(len(field_dir)), rcond=None)
    n_mat = n_vec.reshape(3, 3)
    if np.linalg.det(n_mat) < 0:
        n_mat = -n_mat
    u, _, vt = np.linalg.svd(n_mat)
    rotation = u @ vt
    if np.linalg.det(rotation) < 0:  # the dip is near zero and N is noise: start from no rotation
        return np.eye(3)
    return rotation
