"""A moving device with a gyroscope whose readings integrate exactly to its attitude (tests of magnet.fusion)."""

from __future__ import annotations

import numpy as np

from magnet import frames
from magnet.frames import quaternion_multiply, quaternion_to_matrix

RATE_HZ = 100.0
FIELD_NED_UT = 50.0 * np.array([np.cos(np.radians(65.0)), 0.0, np.sin(np.radians(65.0))])


def rotating_device(seconds: float = 60.0, seed: int = 0):
    """(gyr rad/s, acc m/s^2, mag uT, true body->NED quats), all (N, ...): a device turning and rocking.

    The gyroscope readings integrate exactly to the attitude (q_k+1 = q_k * exp(w dt / 2)), body frame."""
    dt = 1.0 / RATE_HZ
    t = np.arange(0.0, seconds, dt)
    gyr = np.column_stack([0.6 * np.sin(0.7 * t), 0.5 * np.cos(0.45 * t + 1.0), 0.4 + 0.3 * np.sin(0.2 * t)])
    gyr[: int(2 * RATE_HZ)] = 0.0  # still at first, as a device switched on
    quats = np.empty((len(t), 4))
    q = frames.w_positive(frames.euler_to_quaternion(30.0, 5.0, -10.0))
    for k, w in enumerate(gyr):
        quats[k] = q
        angle = np.linalg.norm(w) * dt
        axis = w / np.linalg.norm(w) if angle > 0 else np.zeros(3)
        q = quaternion_multiply(q, np.concatenate([[np.cos(angle / 2)], np.sin(angle / 2) * axis]))
    rot = quaternion_to_matrix(quats)
    acc = np.einsum("nji,j->ni", rot, [0.0, 0.0, -9.80665])
    mag = np.einsum("nji,j->ni", rot, FIELD_NED_UT)
    noise = np.random.default_rng(seed)
    return (
        gyr + noise.normal(0, 0.002, gyr.shape),
        acc + noise.normal(0, 0.02, acc.shape),
        mag + noise.normal(0, 0.1, mag.shape),
        quats,
    )
