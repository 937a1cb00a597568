"""Rotations between the body frame and the local north-east-down (NED) frame.

Frames (docs/design.md, "Conventions"): body x forward, y right, z down; NED x north (geographic), y east, z down.

Attitude is given by Euler angles in the aerospace Z-Y-X order: yaw (heading, clockwise from north), then pitch
(positive nose up), then roll (positive right side down). The body-to-NED rotation is

    R = Rz(yaw) @ Ry(pitch) @ Rx(roll)

so a vector v_body expressed in NED is R @ v_body, and a NED vector (the Earth's field, gravity) expressed in the body
frame is R.T @ v_ned. All angles in degrees; every function broadcasts over leading dimensions, so angles of shape
(N,) give matrices of shape (N, 3, 3).
"""

from __future__ import annotations

import numpy as np
import numpy.typing as npt


def _axis_rotation(angle_deg: np.ndarray, axis: int) -> np.ndarray:
    """Elementary rotation matrices (..., 3, 3) about body axis 0 (x), 1 (y) or 2 (z), right-handed."""
    a = np.radians(np.asarray(angle_deg, dtype=float))
    c, s = np.cos(a), np.sin(a)
    one, zero = np.ones_like(a), np.zeros_like(a)
    if axis == 0:
        rows = [[one, zero, zero], [zero, c, -s], [zero, s, c]]
    elif axis == 1:
        rows = [[c, zero, s], [zero, one, zero], [-s, zero, c]]
    else:
        rows = [[c, -s, zero], [s, c, zero], [zero, zero, one]]
    return np.stack([np.stack(row, axis=-1) for row in rows], axis=-2)


def euler_to_matrix(yaw_deg: npt.ArrayLike, pitch_deg: npt.ArrayLike, roll_deg: npt.ArrayLike) -> np.ndarray:
    """Body-to-NED rotation R = Rz(yaw) Ry(pitch) Rx(roll), shape broadcast(angles) + (3, 3)."""
    yaw, pitch, roll = np.broadcast_arrays(*(np.asarray(x, dtype=float) for x in (yaw_deg, pitch_deg, roll_deg)))
    return _axis_rotation(yaw, 2) @ _axis_rotation(pitch, 1) @ _axis_rotation(roll, 0)


def matrix_to_euler(matrix: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Inverse of :func:`euler_to_matrix`: (yaw in [0, 360), pitch in [-90, 90], roll in (-180, 180]) in degrees.

    ``matrix`` has shape (..., 3, 3). At pitch +-90 deg yaw and roll are not separable; the split returned there is
    arbitrary but still reproduces the matrix.
    """
    r = np.asarray(matrix, dtype=float)
    pitch = np.degrees(np.arcsin(np.clip(-r[..., 2, 0], -1.0, 1.0)))
    yaw = np.degrees(np.arctan2(r[..., 1, 0], r[..., 0, 0]))
    roll = np.degrees(np.arctan2(r[..., 2, 1], r[..., 2, 2]))
    return np.mod(yaw, 360.0), pitch, roll


def ned_to_body(matrix: np.ndarray, vector_ned: np.ndarray) -> np.ndarray:
    """Express NED vectors in the body frame: R.T @ v. matrix (..., 3, 3), vector (..., 3) or (3,) -> (..., 3)."""
    return np.einsum("...ji,...j->...i", np.asarray(matrix, dtype=float), np.asarray(vector_ned, dtype=float))


def body_to_ned(matrix: np.ndarray, vector_body: np.ndarray) -> np.ndarray:
    """Express body vectors in NED: R @ v. matrix (..., 3, 3), vector (..., 3) -> (..., 3)."""
    return np.einsum("...ij,...j->...i", np.asarray(matrix, dtype=float), np.asarray(vector_body, dtype=float))


def axis_angle_matrix(axis: np.ndarray, angle_deg: npt.ArrayLike) -> np.ndarray:
    """Rotation by ``angle_deg`` about unit-normalised ``axis`` (..., 3) (Rodrigues' formula) -> (..., 3, 3)."""
    k = np.asarray(axis, dtype=float)
    norm = np.linalg.norm(k, axis=-1, keepdims=True)
    if np.any(norm == 0):
        raise ValueError("rotation axis must be a non-zero vector")
    k = k / norm
    a = np.radians(np.asarray(angle_deg, dtype=float))[..., None, None]
    zero = np.zeros(k.shape[:-1])
    cross = np.stack(
        [
            np.stack([zero, -k[..., 2], k[..., 1]], axis=-1),
            np.stack([k[..., 2], zero, -k[..., 0]], axis=-1),
            np.stack([-k[..., 1], k[..., 0], zero], axis=-1),
        ],
        axis=-2,
    )
    eye = np.eye(3)
    return eye + np.sin(a) * cross + (1.0 - np.cos(a)) * (cross @ cross)


def quaternion_to_matrix(quat_wxyz: np.ndarray) -> np.ndarray:
    """Rotation matrices (..., 3, 3) from quaternions (..., 4) ordered w, x, y, z (normalised here)."""
    q = np.asarray(quat_wxyz, dtype=float)
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    w, x, y, z = np.moveaxis(q, -1, 0)
    return np.stack(
        [
            np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], axis=-1),
            np.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], axis=-1),
            np.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], axis=-1),
        ],
        axis=-2,
    )


def random_rotations(count: int, rng: np.random.Generator) -> np.ndarray:
    """``count`` rotations drawn uniformly over SO(3) (normalised Gaussian quaternions), shape (count, 3, 3)."""
    return quaternion_to_matrix(rng.standard_normal((count, 4)))


def rotation_angle_deg(matrix: np.ndarray) -> np.ndarray:
    """Angle of the rotation (..., 3, 3) in degrees, in [0, 180]."""
    r = np.asarray(matrix, dtype=float)
    cos_angle = (np.trace(r, axis1=-2, axis2=-1) - 1.0) / 2.0
    return np.degrees(np.arccos(np.clip(cos_angle, -1.0, 1.0)))


# --------------------------------------------------------------------------------------------------- quaternions
# Hamilton quaternions ordered w, x, y, z; a unit quaternion q of an attitude is body-to-NED: v_ned = q v_body q*,
# the same rotation as ``quaternion_to_matrix(q)``.


def quaternion_multiply(p: np.ndarray, q: np.ndarray) -> np.ndarray:
    """Hamilton product p q of quaternions (..., 4) wxyz (broadcast) -> (..., 4): rotate by q, then by p."""
    pw, px, py, pz = np.moveaxis(np.asarray(p, dtype=float), -1, 0)
    qw, qx, qy, qz = np.moveaxis(np.asarray(q, dtype=float), -1, 0)
    return np.stack(
        [
            pw * qw - px * qx - py * qy - pz * qz,
            pw * qx + px * qw + py * qz - pz * qy,
            pw * qy - px * qz + py * qw + pz * qx,
            pw * qz + px * qy - py * qx + pz * qw,
        ],
        axis=-1,
    )


def quaternion_conjugate(q: np.ndarray) -> np.ndarray:
    """Conjugate (the inverse of a unit quaternion), (..., 4) wxyz."""
    return np.asarray(q, dtype=float) * np.array([1.0, -1.0, -1.0, -1.0])


def euler_to_quaternion(yaw_deg: npt.ArrayLike, pitch_deg: npt.ArrayLike, roll_deg: npt.ArrayLike) -> np.ndarray:
    """Body-to-NED unit quaternion (..., 4) wxyz of Rz(yaw) Ry(pitch) Rx(roll) (degrees, any values, broadcast);
    continuous in the angles (no sign flips), so a smooth angle history gives a smooth quaternion history."""
    yaw, pitch, roll = np.broadcast_arrays(
        *(np.radians(np.asarray(a, dtype=float)) / 2.0 for a in (yaw_deg, pitch_deg, roll_deg))
    )
    cy, sy, cp, sp, cr, sr = np.cos(yaw), np.sin(yaw), np.cos(pitch), np.sin(pitch), np.cos(roll), np.sin(roll)
    return np.stack(
        [
            cy * cp * cr + sy * sp * sr,
            cy * cp * sr - sy * sp * cr,
            cy * sp * cr + sy * cp * sr,
            sy * cp * cr - cy * sp * sr,
        ],
        axis=-1,
    )


def quaternion_to_euler(quat_wxyz: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(yaw in [0, 360), pitch in [-90, 90], roll in (-180, 180]) degrees of body-to-NED quaternions (..., 4)."""
    return matrix_to_euler(quaternion_to_matrix(quat_wxyz))


def rotation_vector_to_quaternion(rotvec_rad: np.ndarray) -> np.ndarray:
    """Unit quaternions (..., 4) of rotation vectors (..., 3) (axis times angle in radians): the exponential map."""
    v = np.asarray(rotvec_rad, dtype=float)
    angle = np.linalg.norm(v, axis=-1, keepdims=True)
    half = angle / 2.0
    # sin(half) / angle, with its limit 1/2 - angle^2/48 near zero
    scale = np.where(angle > 1e-8, np.sin(half) / np.where(angle > 1e-8, angle, 1.0), 0.5 - angle**2 / 48.0)
    return np.concatenate([np.cos(half), v * scale], axis=-1)


def quaternion_to_rotation_vector(quat_wxyz: np.ndarray) -> np.ndarray:
    """Rotation vectors (..., 3), radians, angle in [0, pi], of quaternions (..., 4) (normalised here): the log map
    of the shorter of q and -q."""
    q = np.asarray(quat_wxyz, dtype=float)
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    q = np.where(q[..., :1] < 0, -q, q)
    w, xyz = q[..., :1], q[..., 1:]
    sin_half = np.linalg.norm(xyz, axis=-1, keepdims=True)
    angle = 2.0 * np.arctan2(sin_half, w)
    scale = np.where(sin_half > 1e-12, angle / np.where(sin_half > 1e-12, sin_half, 1.0), 2.0 / np.maximum(w, 1e-12))
    return xyz * scale
