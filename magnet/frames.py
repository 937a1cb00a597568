"""Frames, rotations and quaternions: the one place where the project's conventions are written (docs/frames.md).

Frames:
- body, FRD: x forward, y right, z down. Every sensor vector once its chip's axes are mapped (named alignments below).
- earth, NED: x north, y east, z down. North is geographic unless a name says magnetic (``to_magnetic_ned``).
- FLU / ENU: body x forward, y left, z up; earth x east, y north, z up. ROS 2's frames (REP-103) and the vqf filter's
  (``magnet.attitude.fusion``; its north is the field's). A body vector FRD -> FLU is (x, -y, -z) (``frd_flu``), an
  earth vector NED -> ENU is (e, n, -d) (``ned_enu``), an attitude FRD -> NED to FLU -> ENU is ``ned_enu_attitude``:
  each map is its own inverse.

Rotations: an attitude is the body -> earth rotation R = Rz(yaw) @ Ry(pitch) @ Rx(roll) (aerospace Z-Y-X: yaw is the
heading of body x clockwise from north, pitch nose up positive, roll right side down positive; degrees), so
v_ned = R @ v_body and v_body = R.T @ v_ned. Quaternions are Hamilton, ordered w, x, y, z (ROS's messages order x, y,
z, w: reordered at that boundary); the unit quaternion q of an attitude is body -> earth, v_ned = q v_body q*, the
same rotation as ``quaternion_to_matrix(q)``; q and -q are one rotation ("w >= 0" picks the first).

Named alignments: a chip's axes -> body axes, v_body = R @ v_chip, from the autopilots' numbered table
(``ROTATIONS``) or a name such as ``roll180_yaw90`` (``orientation_matrix``). Every function broadcasts over leading
dimensions: angles (N,) give matrices (N, 3, 3) and quaternions (N, 4).
"""

from __future__ import annotations

import math
import re
from typing import Any

import numpy as np
import numpy.typing as npt

from magnet import _kernels

# ------------------------------------------------------------------------------------------ matrices, Euler angles


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
    arbitrary but still reproduces the matrix."""
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


def ned_to_body_euler(
    vector_ned: np.ndarray, yaw_deg: np.ndarray, pitch_deg: np.ndarray, roll_deg: np.ndarray
) -> np.ndarray:
    """R^T v for R = Rz(yaw) Ry(pitch) Rx(roll), without building matrices: vector (3,) or (..., 3) in NED, angles
    broadcastable, result (..., 3) in body axes. The fast path of the simulators (three elementary rotations)."""
    v = np.asarray(vector_ned, dtype=float)
    y, p, r = (np.radians(np.asarray(a, dtype=float)) for a in (yaw_deg, pitch_deg, roll_deg))
    cy, sy, cp, sp, cr, sr = np.cos(y), np.sin(y), np.cos(p), np.sin(p), np.cos(r), np.sin(r)
    n, e, d = v[..., 0], v[..., 1], v[..., 2]
    x1 = cy * n + sy * e  # Rz^T
    y1 = -sy * n + cy * e
    x2 = cp * x1 - sp * d  # Ry^T
    z2 = sp * x1 + cp * d
    y3 = cr * y1 + sr * z2  # Rx^T
    z3 = -sr * y1 + cr * z2
    return np.stack(np.broadcast_arrays(x2, y3, z3), axis=-1)


def _rodrigues(unit_axis: np.ndarray, angle_rad: np.ndarray) -> np.ndarray:
    """I + sin(a) K + (1 - cos(a)) K^2, K the cross-product matrix of unit axes (..., 3); angles (...): (..., 3, 3)."""
    k = unit_axis
    zero = np.zeros(k.shape[:-1])
    rows = ([zero, -k[..., 2], k[..., 1]], [k[..., 2], zero, -k[..., 0]], [-k[..., 1], k[..., 0], zero])
    cross = np.stack([np.stack(row, axis=-1) for row in rows], axis=-2)
    a = np.asarray(angle_rad)[..., None, None]
    return np.eye(3) + np.sin(a) * cross + (1.0 - np.cos(a)) * (cross @ cross)


def axis_angle_matrix(axis: np.ndarray, angle_deg: npt.ArrayLike) -> np.ndarray:
    """Rotation by ``angle_deg`` about unit-normalised ``axis`` (..., 3) (Rodrigues' formula) -> (..., 3, 3)."""
    k = np.asarray(axis, dtype=float)
    norm = np.linalg.norm(k, axis=-1, keepdims=True)
    if np.any(norm == 0):
        raise ValueError("rotation axis must be a non-zero vector")
    return _rodrigues(k / norm, np.radians(np.asarray(angle_deg, dtype=float)))


def rotation_vector_to_matrix(rotvec_rad: np.ndarray) -> np.ndarray:
    """Rotation matrices (..., 3, 3) exp([w]x) of rotation vectors w (..., 3) (axis times angle, radians); zero
    vectors give the identity."""
    w = np.asarray(rotvec_rad, dtype=float)
    angle = np.linalg.norm(w, axis=-1)
    return _rodrigues(w / np.where(angle > 0, angle, 1.0)[..., None], angle)


def quaternion_to_matrix(quat_wxyz: np.ndarray) -> np.ndarray:
    """Rotation matrices (..., 3, 3) from quaternions (..., 4) ordered w, x, y, z (normalised here)."""
    q = np.asarray(quat_wxyz, dtype=float)
    q = q / np.sqrt(np.add.reduce(q * q, axis=-1, keepdims=True))  # np.linalg.norm's sum, without its overhead
    w, x, y, z = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    out = np.empty((*q.shape[:-1], 3, 3))
    out[..., 0, 0] = 1 - 2 * (y * y + z * z)
    out[..., 0, 1] = 2 * (x * y - w * z)
    out[..., 0, 2] = 2 * (x * z + w * y)
    out[..., 1, 0] = 2 * (x * y + w * z)
    out[..., 1, 1] = 1 - 2 * (x * x + z * z)
    out[..., 1, 2] = 2 * (y * z - w * x)
    out[..., 2, 0] = 2 * (x * z - w * y)
    out[..., 2, 1] = 2 * (y * z + w * x)
    out[..., 2, 2] = 1 - 2 * (x * x + y * y)
    return out


def random_rotations(count: int, rng: np.random.Generator) -> np.ndarray:
    """``count`` rotations drawn uniformly over SO(3) (normalised Gaussian quaternions), shape (count, 3, 3)."""
    return quaternion_to_matrix(rng.standard_normal((count, 4)))


def rotation_angle_deg(matrix: np.ndarray) -> np.ndarray:
    """Angle of the rotation (..., 3, 3) in degrees, in [0, 180]."""
    r = np.asarray(matrix, dtype=float)
    cos_angle = (np.trace(r, axis1=-2, axis2=-1) - 1.0) / 2.0
    return np.degrees(np.arccos(np.clip(cos_angle, -1.0, 1.0)))


# --------------------------------------------------------------------------------------------------- quaternions


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


def w_positive(q: np.ndarray) -> np.ndarray:
    """Quaternions (..., 4) negated where w < 0 (the same rotation); a product with the sign, several times faster
    than ``np.where`` broadcasting the condition over the four components."""
    return q * np.where(q[..., :1] < 0, -1.0, 1.0)


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


def down_in_body(quat_wxyz: np.ndarray) -> np.ndarray:
    """The NED down direction in body axes (..., 3), unit, from body -> NED quaternions (..., 4): R^T (0, 0, 1)."""
    return quaternion_to_matrix(quat_wxyz)[..., 2, :]


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


# ------------------------------------------------------------------------------------------- frame conversions

_FLIP_YZ = np.array([1.0, -1.0, -1.0])
#: _FLIP_YZ repeated for 2**15 rows (a drain's 30,000 samples): (S, 3) flipped in one contiguous multiply, a third of
#: the instructions of numpy's broadcast of (3,) over rows of 3 (the same products, to the bit)
_FLIP_ROWS = np.tile(_FLIP_YZ, 1 << 15)
_HALF_SQRT2 = math.sqrt(0.5)
#: NED <-> ENU axes (half a turn about the north-east diagonal) and FRD <-> FLU (half a turn about x), as w, x, y, z
_Q_NED_ENU = np.array([0.0, _HALF_SQRT2, _HALF_SQRT2, 0.0])
_Q_FRD_FLU = np.array([0.0, 1.0, 0.0, 0.0])
#: q -> q_NED_ENU q q_FRD_FLU is linear in q: row k is the image of the k-th unit quaternion, so that it is q @ this
_NED_ENU_ATTITUDE = np.stack([quaternion_multiply(quaternion_multiply(_Q_NED_ENU, e), _Q_FRD_FLU) for e in np.eye(4)])


def frd_flu(vectors: np.ndarray) -> np.ndarray:
    """Body vectors (..., 3) FRD as FLU, or back: (x, y, z) -> (x, -y, -z)."""
    v = np.asarray(vectors, dtype=float)
    if v.ndim == 2 and v.shape[1] == 3 and 192 <= v.size <= _FLIP_ROWS.size:
        return np.multiply(v.reshape(-1), _FLIP_ROWS[: v.size]).reshape(v.shape)
    return v * _FLIP_YZ


def ned_enu(vectors: np.ndarray) -> np.ndarray:
    """Earth vectors (..., 3) NED as ENU, or back: (a, b, c) -> (b, a, -c)."""
    v = np.asarray(vectors, dtype=float)
    return np.stack([v[..., 1], v[..., 0], -v[..., 2]], axis=-1)


def ned_enu_attitude(quat_wxyz: np.ndarray) -> np.ndarray:
    """Attitudes (..., 4) body FLU -> ENU (vqf's output, a ROS orientation in w, x, y, z order) as body FRD -> NED,
    or back (the map is its own inverse); w >= 0."""
    return w_positive(np.asarray(quat_wxyz, dtype=float) @ _NED_ENU_ATTITUDE)


def rotate_heading(quat_wxyz: np.ndarray, angle_deg: npt.ArrayLike) -> np.ndarray:
    """Quaternions (..., 4) turned by ``angle_deg`` (broadcast to (...)) about NED down (magnetic -> true north: the
    declination): the product (cos h, 0, 0, sin h) q, h half the angle, then w >= 0; compiled, one pass
    (``magnet._kernels.turn_about_down``)."""
    quat = np.asarray(quat_wxyz, dtype=float)
    angle = np.asarray(angle_deg, dtype=float)
    if quat.ndim != 2 or angle.shape != quat.shape[:1]:  # broadcast (the compass's (S, 4) and (S,) need not be)
        shape = np.broadcast_shapes(quat.shape[:-1], angle.shape)
        flat = rotate_heading(np.broadcast_to(quat, (*shape, 4)).reshape(-1, 4), np.broadcast_to(angle, shape).ravel())
        return flat.reshape(*shape, 4)
    out = np.empty_like(quat)
    _kernels.turn_about_down(quat, angle, out)
    return out


def to_magnetic_ned(vel_ned_ms: np.ndarray, declination_deg: float | np.ndarray) -> np.ndarray:
    """Vectors (N, 3) (velocities, m/s) in geographic NED turned into magnetic NED (north along the field's horizontal
    part): rotated by -declination about down. ``declination_deg`` one number or (N,); NaN rows stay NaN."""
    angle = np.radians(np.asarray(declination_deg, dtype=float))
    c, s = np.cos(angle), np.sin(angle)
    v = np.asarray(vel_ned_ms, dtype=float)
    return np.stack([c * v[:, 0] + s * v[:, 1], -s * v[:, 0] + c * v[:, 1], v[:, 2]], axis=-1)


# --------------------------------------------------------------------------------------------- named alignments

#: orientation number -> (roll, pitch, yaw) degrees, as both PX4 and ArduPilot number them (ArduPilot
#: ``COMPASS_ORIENTn``, PX4 ``CAL_MAGn_ROT`` and ``SENS_BOARD_ROT``); 38 and those above 40 differ between them
ROTATIONS: dict[int, tuple[float, float, float]] = {
    0: (0, 0, 0),
    1: (0, 0, 45),
    2: (0, 0, 90),
    3: (0, 0, 135),
    4: (0, 0, 180),
    5: (0, 0, 225),
    6: (0, 0, 270),
    7: (0, 0, 315),
    8: (180, 0, 0),
    9: (180, 0, 45),
    10: (180, 0, 90),
    11: (180, 0, 135),
    12: (0, 180, 0),
    13: (180, 0, 225),
    14: (180, 0, 270),
    15: (180, 0, 315),
    16: (90, 0, 0),
    17: (90, 0, 45),
    18: (90, 0, 90),
    19: (90, 0, 135),
    20: (270, 0, 0),
    21: (270, 0, 45),
    22: (270, 0, 90),
    23: (270, 0, 135),
    24: (0, 90, 0),
    25: (0, 270, 0),
    26: (0, 180, 90),
    27: (0, 180, 270),
    28: (90, 90, 0),
    29: (180, 90, 0),
    30: (270, 90, 0),
    31: (90, 180, 0),
    32: (270, 180, 0),
    33: (90, 270, 0),
    34: (180, 270, 0),
    35: (270, 270, 0),
    36: (90, 180, 90),
    37: (90, 0, 270),
    39: (0, 315, 0),
    40: (90, 315, 0),
}
_AXES = {"roll": 0, "pitch": 1, "yaw": 2}
_TOKEN = re.compile(r"(roll|pitch|yaw)_?(\d+)")


def rotation_matrix(number: int) -> np.ndarray:
    """(3, 3) sensor -> body rotation of orientation ``number``; ValueError for a number not in ``ROTATIONS``."""
    if number not in ROTATIONS:
        known = ", ".join(str(n) for n in ROTATIONS)
        raise ValueError(f"orientation {number} is not one magnet knows (known: {known})")
    roll, pitch, yaw = ROTATIONS[number]
    return euler_to_matrix(yaw, pitch, roll)


def nearest_rotation(matrix: np.ndarray) -> tuple[int, float]:
    """(orientation number, angle in degrees between it and ``matrix`` (3, 3), a rotation)."""
    best = min(ROTATIONS, key=lambda n: float(rotation_angle_deg(rotation_matrix(n).T @ matrix)))
    return best, float(rotation_angle_deg(rotation_matrix(best).T @ matrix))


def _rotation_from_name(name: str) -> np.ndarray:
    text = name.strip().lower()
    text = text.removeprefix("rotation_")
    if text in ("", "none", "identity"):
        return np.eye(3)
    matrix = np.eye(3)
    rest = _TOKEN.sub("", text).strip("_+ ,")
    if rest.replace("_", "").replace("+", "").replace(" ", "").replace(",", ""):
        raise ValueError(
            f"unknown orientation {name!r}: use names such as 'none', 'yaw90', 'roll180', "
            "'roll180_yaw90', 'pitch270' (ArduPilot ROTATION_* names) or 9 numbers of a 3x3 matrix"
        )
    for axis, degrees in _TOKEN.findall(text):
        if int(degrees) % 45:
            raise ValueError(f"orientation {name!r}: angles must be multiples of 45 degrees, got {degrees}")
        matrix = _axis_rotation(np.asarray(float(degrees)), _AXES[axis]) @ matrix
    return np.round(matrix, 12)


def orientation_matrix(orientation: Any) -> np.ndarray:
    """The 3x3 matrix R that maps a vector in the chip's marked axes to the body frame: v_body = R @ v_chip.

    ``orientation`` is None (chip axes are the body axes), a name in ArduPilot's ROTATION_* style (``"yaw90"``,
    ``"roll180"``, ``"ROTATION_ROLL_180_YAW_90"``, ``"pitch270"``; rotations are applied in the order written, so
    ``roll180_yaw90`` = Rz(90) @ Rx(180), as ArduPilot does and as ``ROTATIONS`` reads), a 3x3 matrix, or 9 numbers
    (row-major, or a string of them separated by commas). The matrix must be a proper rotation (orthonormal,
    determinant +1).
    """
    if orientation is None:
        return np.eye(3)
    if isinstance(orientation, str) and not re.search(r"[a-z]", orientation.lower()):
        orientation = [float(v) for v in orientation.replace(";", ",").split(",") if v.strip()]
    if isinstance(orientation, str):
        return _rotation_from_name(orientation)
    matrix = np.asarray(orientation, dtype=float)
    if matrix.size != 9:
        raise ValueError(f"an orientation matrix needs 9 numbers (3x3 row-major), got {matrix.size}")
    matrix = matrix.reshape(3, 3)
    if not np.allclose(matrix @ matrix.T, np.eye(3), atol=1e-6) or np.linalg.det(matrix) < 0:
        raise ValueError(
            f"an orientation matrix must be a rotation (orthonormal rows, determinant +1); got {matrix.tolist()}"
        )
    return matrix
