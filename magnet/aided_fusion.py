"""The gyroscope-aided filter fed with velocity: vqf run a little behind the newest sample (design: docs/design.md,
"Heading in motion", velocity aiding; the acceleration itself: ``magnet.aiding``).

The linear acceleration at time t is known only once a velocity fix after t + h has arrived (a few tenths of a
second later). So the filter (vqf, in its own frames: z-up body, ENU with magnetic north) is fed a sample only when
its acceleration is known, or when it is ``max_lag_s`` old (a receiver that went quiet: fed as it is). Each sample
is fed as acc - R^T a_enu, R the latest attitude this filter gave that sample (carried forward, below). The attitude
of a sample not yet fed is the filter's latest attitude carried forward by the gyroscope (less the filter's bias
estimate) over the samples in between: q_i = q_filter * prod_j exp((w_j - b) dt / 2), a fraction of a second of
integration, so the newest sample is answered at once (causal, no delay on the output).
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import vqf

from magnet.aiding import VelocityFixes

#: a batch is taken this many seconds at a time (a whole log in one call is answered as if it came in pieces)
CHUNK_S = 0.05
#: the longest a sample waits for its acceleration before it is fed as it is (s)
MAX_LAG_S = 1.0


def _rotation_vqf(q: np.ndarray) -> np.ndarray:
    """Rotation matrices (N, 3, 3) of quaternions (N, 4) w, x, y, z (unit)."""
    w, x, y, z = q[:, 0], q[:, 1], q[:, 2], q[:, 3]
    return np.stack(
        [
            np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], axis=-1),
            np.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], axis=-1),
            np.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], axis=-1),
        ],
        axis=-2,
    )


def _in_body(quat_vqf: np.ndarray, a_ned: np.ndarray) -> np.ndarray:
    """Accelerations (N, 3) magnetic NED in vqf's body frame (N, 3), by vqf quaternions (N, 4) body -> ENU."""
    a_enu = np.column_stack([a_ned[:, 1], a_ned[:, 0], -a_ned[:, 2]])
    return np.einsum("nji,nj->ni", _rotation_vqf(quat_vqf), a_enu)


def body_acceleration(quat_vqf: np.ndarray, t_s: np.ndarray, vel_ned_ms: np.ndarray) -> np.ndarray:
    """The linear acceleration (N, 3) of a whole log in vqf's body frame: the velocity's (magnetic NED, held rows,
    NaN where unknown) with every fix known, turned by the attitudes ``quat_vqf`` (N, 4)."""
    fixes = VelocityFixes(max_fixes=max(len(t_s), 2))
    fixes.observe(np.asarray(t_s, dtype=float), vel_ned_ms)
    return _in_body(np.asarray(quat_vqf, dtype=float), fixes.acceleration(np.asarray(t_s, dtype=float)))


def carry_forward(start: np.ndarray, gyr: np.ndarray, bias: np.ndarray, period_s: float) -> np.ndarray:
    """Quaternions (N, 4) from ``start`` (4,) turned by each body rate (N, 3) rad/s less ``bias`` (3,) over one
    period in turn (right products: body-frame rates), as vqf integrates them."""
    out = np.empty((len(gyr), 4))
    w, x, y, z = (float(v) for v in start)
    for i, rate in enumerate((np.asarray(gyr, dtype=float) - bias).tolist()):
        norm = math.sqrt(rate[0] ** 2 + rate[1] ** 2 + rate[2] ** 2)
        angle = norm * period_s / 2.0
        c, s = math.cos(angle), (math.sin(angle) / norm if norm > 0 else 0.0)
        a, b, d = rate[0] * s, rate[1] * s, rate[2] * s
        w, x, y, z = (w * c - x * a - y * b - z * d, w * a + x * c + y * d - z * b, w * b - x * d + y * c + z * a,
                      w * d + x * b - y * a + z * c)  # fmt: skip
        out[i] = (w, x, y, z)
    return out


class AidedFilter:
    """vqf with velocity aiding for one device (see the module docstring). Inputs in vqf's frames; velocities in
    magnetic NED m/s; times in seconds."""

    def __init__(self, period_s: float, params: dict[str, Any], max_lag_s: float = MAX_LAG_S) -> None:
        self.period_s, self.params, self.max_lag_s = period_s, params, max_lag_s
        self.filter = vqf.VQF(period_s, **params)
        self.fixes = VelocityFixes()
        self.pending: list[np.ndarray] = []  # rows t, gyr (3), acc (3), field (3), quat given (4): (n, 14)
        self.disturbed = False

    def restart(self) -> None:
        self.filter.resetState()
        self.fixes, self.pending, self.disturbed = VelocityFixes(), [], False

    def update(
        self, gyr: np.ndarray, acc: np.ndarray, field: np.ndarray, t_s: np.ndarray, vel_ned_ms: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        """One batch (N samples, vqf frame, C-contiguous float64): (vqf quaternions (N, 4) body -> ENU, magnetic
        disturbance flags (N,)) for its samples. Taken ``CHUNK_S`` at a time, as if they had come so."""
        step = max(1, round(CHUNK_S / self.period_s))
        parts = [
            self._chunk(
                gyr[i : i + step], acc[i : i + step], field[i : i + step], t_s[i : i + step], vel_ned_ms[i : i + step]
            )
            for i in range(0, len(gyr), step)
        ]
        if not parts:
            return np.zeros((0, 4)), np.zeros(0, dtype=bool)
        return np.vstack([q for q, _ in parts]), np.concatenate([d for _, d in parts])

    def _chunk(
        self, gyr: np.ndarray, acc: np.ndarray, field: np.ndarray, t_s: np.ndarray, vel_ned_ms: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        self.fixes.observe(t_s, vel_ned_ms)
        self._feed(float(t_s[-1]))
        rows = np.column_stack([t_s, gyr, acc, field, np.full((len(t_s), 4), np.nan)])
        table = np.vstack([*self.pending, rows])
        start = np.asarray(self.filter.getQuat9D(), dtype=float)
        bias = np.asarray(self.filter.getBiasEstimate()[0], dtype=float)
        quats = carry_forward(start, table[:, 1:4], bias, self.period_s)
        table[:, 10:] = quats
        self.pending = [table]
        self._feed(float(t_s[-1]))
        return quats[-len(t_s) :], np.full(len(t_s), self.disturbed)

    def _feed(self, now_s: float) -> None:
        """Feed the pending samples whose acceleration is known (or that waited ``max_lag_s``), in order."""
        if not self.pending:
            return
        table = np.vstack(self.pending)
        ready = (table[:, 0] <= self.fixes.known_until_s) | (table[:, 0] < now_s - self.max_lag_s)
        ready &= np.all(np.isfinite(table[:, 10:]), axis=1)
        count = int(np.argmin(ready)) if not ready.all() else len(table)
        if count == 0:
            return
        fed, self.pending = table[:count], [table[count:]] if count < len(table) else []
        acc = fed[:, 4:7] - _in_body(fed[:, 10:], self.fixes.acceleration(fed[:, 0]))
        gyr, field = np.ascontiguousarray(fed[:, 1:4]), np.ascontiguousarray(fed[:, 7:10])
        out = self.filter.updateBatch(gyr, np.ascontiguousarray(acc), field)
        self.disturbed = bool(np.asarray(out["magDistDetected"]).reshape(-1)[-1])
