"""A moving device with a gyroscope whose readings integrate exactly to its attitude (tests of
magnet.attitude.fusion)."""

from __future__ import annotations

import numpy as np

from magnet import frames
from magnet.frames import quaternion_to_matrix
from magnet.simulator import SensorErrors, SimulatedRun, SimulatorConfig, Trajectory, simulate

RATE_HZ = 100.0
FIELD_NED_UT = 50.0 * np.array([np.cos(np.radians(65.0)), 0.0, np.sin(np.radians(65.0))])

#: the noise-free gyroscope and attitude of the longest run integrated so far: a shorter run is its first samples
#: (the motion depends on time only, and the attitude is integrated sample by sample from the same start), so the
#: tests that ask for 5, 20, 40, 60 and 120 s integrate the attitude once
_LONGEST: list[tuple[np.ndarray, np.ndarray]] = []


def _motion(count: int) -> tuple[np.ndarray, np.ndarray]:
    """The first ``count`` noise-free gyroscope readings (rad/s) and body->NED quaternions (copies)."""
    if not _LONGEST or len(_LONGEST[0][0]) < count:
        dt = 1.0 / RATE_HZ
        t = np.arange(count) * dt
        gyr = np.column_stack([0.6 * np.sin(0.7 * t), 0.5 * np.cos(0.45 * t + 1.0), 0.4 + 0.3 * np.sin(0.2 * t)])
        gyr[: int(2 * RATE_HZ)] = 0.0  # still at first, as a device switched on
        rate = np.linalg.norm(gyr, axis=1)
        axis = np.divide(gyr, rate[:, None], out=np.zeros_like(gyr), where=rate[:, None] > 0)
        half = rate * dt / 2
        steps = np.column_stack([np.cos(half), np.sin(half)[:, None] * axis]).tolist()  # exp(w dt / 2)
        # the Hamilton product q * step sample by sample, on floats (a numpy call per sample costs 20 times more)
        pw, px, py, pz = frames.w_positive(frames.euler_to_quaternion(30.0, 5.0, -10.0)).tolist()
        quats = []
        for qw, qx, qy, qz in steps:
            quats.append((pw, px, py, pz))
            pw, px, py, pz = (
                pw * qw - px * qx - py * qy - pz * qz,
                pw * qx + px * qw + py * qz - pz * qy,
                pw * qy - px * qz + py * qw + pz * qx,
                pw * qz + px * qy - py * qx + pz * qw,
            )
        _LONGEST[:] = [(gyr, np.array(quats))]
    gyr, quats = _LONGEST[0]
    return gyr[:count].copy(), quats[:count].copy()


def rotating_device(seconds: float = 60.0, seed: int = 0):
    """(gyr rad/s, acc m/s^2, mag uT, true body->NED quats), all (N, ...): a device turning and rocking.

    The gyroscope readings integrate exactly to the attitude (q_k+1 = q_k * exp(w dt / 2)), body frame."""
    gyr, quats = _motion(len(np.arange(0.0, seconds, 1.0 / RATE_HZ)))
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


def phone_boat(seconds: float, rate_hz: float, seed: int = 1) -> SimulatedRun:
    """The simulator's boat with a phone-like sensor drawn as ``magnet bench field`` draws it for ``seed``: turns of
    90-360 deg at 8-15 deg/s at 2-6 m/s, ``seconds`` long at ``rate_hz``."""
    errors = SensorErrors.phone(np.random.default_rng([seed, 26]), 50.0)
    count = int(seconds * rate_hz)
    return simulate(SimulatorConfig(trajectory=Trajectory.BOAT, rate_hz=rate_hz, count=count, errors=errors, seed=seed))
