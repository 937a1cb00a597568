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

import itertools
import math
from typing import Any

import numpy as np
import vqf

from magnet.aiding import VelocityFixes
from magnet.frames import ned_enu, ned_to_body, quaternion_conjugate, quaternion_multiply, quaternion_to_matrix

#: the longest piece of samples answered from one filter state when no fix comes (s)
CHUNK_S = 0.1
#: the longest a sample waits for its acceleration before it is fed as it is (s)
MAX_LAG_S = 1.0


def _in_body(quat_vqf: np.ndarray, a_ned: np.ndarray) -> np.ndarray:
    """Accelerations (N, 3) magnetic NED in vqf's body frame (N, 3), by vqf quaternions (N, 4) body -> ENU."""
    return ned_to_body(quaternion_to_matrix(quat_vqf), ned_enu(a_ned))


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


_T, _GYR, _ACC, _FIELD, _GIVEN, _TURN = (
    slice(0, 1),
    slice(1, 4),
    slice(4, 7),
    slice(7, 10),
    slice(10, 14),
    slice(14, 18),
)
_IDENTITY = np.array([1.0, 0.0, 0.0, 0.0])


class AidedFilter:
    """vqf with velocity aiding for one device (see the module docstring). Inputs in vqf's frames; velocities in
    magnetic NED m/s; times in seconds. ``pending`` (n, 18): the samples not yet fed, each with its time, gyroscope,
    accelerometer, field, the attitude last given to it and its turn since the filter's state (the gyroscope's
    product from the first pending sample to it)."""

    def __init__(
        self, period_s: float, params: dict[str, Any], start: Any = None, max_lag_s: float = MAX_LAG_S
    ) -> None:
        """``start``: a vqf filter to carry on from (the device's filter before its first velocity), else a new one."""
        self.period_s, self.params, self.max_lag_s = period_s, params, max_lag_s
        self.filter = start if start is not None else vqf.VQF(period_s, **params)
        self.fixes = VelocityFixes()
        self.pending = np.zeros((0, 18))
        self.disturbed = False

    def restart(self) -> None:
        self.filter.resetState()
        self.fixes, self.pending, self.disturbed = VelocityFixes(), np.zeros((0, 18)), False

    def update(
        self, gyr: np.ndarray, acc: np.ndarray, field: np.ndarray, t_s: np.ndarray, vel_ned_ms: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        """One batch (N samples, vqf frame, C-contiguous float64): (vqf quaternions (N, 4) body -> ENU, magnetic
        disturbance flags (N,)) for its samples. Taken in pieces that start where a fix arrives or a ``CHUNK_S`` tick
        of time begins, so that the answers do not depend on how the samples were cut into batches."""
        rows = np.column_stack([t_s, gyr, acc, field, np.zeros((len(t_s), 8))])
        tick = np.floor(np.asarray(t_s, dtype=float) / CHUNK_S)
        cuts = np.flatnonzero(self.fixes.arrivals(vel_ned_ms)[1:] | (tick[1:] != tick[:-1])) + 1
        bounds = [0, *cuts.tolist(), len(rows)]
        parts = [self._chunk(rows[a:b], vel_ned_ms[a:b]) for a, b in itertools.pairwise(bounds) if b > a]
        if not parts:
            return np.zeros((0, 4)), np.zeros(0, dtype=bool)
        return np.vstack([q for q, _ in parts]), np.concatenate([d for _, d in parts])

    def _chunk(self, rows: np.ndarray, vel_ned_ms: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """One piece of a batch: rows (n, 18) with time, gyroscope, accelerometer and field filled in."""
        self.fixes.observe(rows[:, 0], vel_ned_ms)
        bias = np.asarray(self.filter.getBiasEstimate()[0], dtype=float)
        before = self.pending[-1, _TURN] if len(self.pending) else _IDENTITY
        rows[:, _TURN] = carry_forward(before, rows[:, _GYR], bias, self.period_s)
        self.pending = np.vstack([self.pending, rows])
        self._give()
        self._feed(float(rows[0, 0]), keep=len(rows))
        self._give()
        return self.pending[-len(rows) :, _GIVEN].copy(), np.full(len(rows), self.disturbed)

    def _give(self) -> None:
        """The attitude of every pending sample: the filter's, turned by the sample's turn."""
        start = np.asarray(self.filter.getQuat9D(), dtype=float)
        self.pending[:, _GIVEN] = quaternion_multiply(start, self.pending[:, _TURN])

    def _feed(self, now_s: float, keep: int) -> None:
        """Feed the pending samples whose acceleration is known (or that waited ``max_lag_s``), in order, but not
        the last ``keep`` (the ones being answered); then count the turns of the others from the new filter state."""
        table = self.pending
        ready = (table[:, 0] <= self.fixes.known_until_s) | (table[:, 0] < now_s - self.max_lag_s)
        count = min(int(np.argmin(ready)) if not ready.all() else len(table), len(table) - keep)
        if count == 0:
            return
        fed, self.pending = table[:count], table[count:].copy()
        acc = fed[:, _ACC] - _in_body(fed[:, _GIVEN], self.fixes.acceleration(fed[:, 0]))
        gyr, field = np.ascontiguousarray(fed[:, _GYR]), np.ascontiguousarray(fed[:, _FIELD])
        out = self.filter.updateBatch(gyr, np.ascontiguousarray(acc), field)
        self.disturbed = bool(np.asarray(out["magDistDetected"]).reshape(-1)[-1])
        turn = quaternion_multiply(quaternion_conjugate(fed[-1, _TURN]), self.pending[:, _TURN])
        self.pending[:, _TURN] = turn / np.linalg.norm(turn, axis=1, keepdims=True)  # rounding would compound
