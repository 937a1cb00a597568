"""A hard iron that moved by a few uT in service (``IronWatch``; docs/field-calibration.md, "Phone realities").

A phone's hard iron steps when a current in its board changes (the screen, the radio, the camera: 1-8 uT) and drifts
as it warms. The refresh collection learns that its device's iron changed only when the record in force misses the
field strength by 15 % (``refresh.CHANGED_PCT``): a few uT is under that, so the refresh that corrects it fitted a
window of 30 s holding samples from before the change, and came 25-35 s after it.

With a gyroscope the record's offset error is measured directly (Kok and Schon 2016, as ``gyro-ellipsoid`` and the
field ladder use it): over a window in which the body turned by P, the corrected field b = B (m) - d, d the offset
error, obeys b(e) = P^T b(s), linear in d: (P^T - I) d = P^T B(s) - B(e). Fitted by least squares over the windows
of the last ``RECENT_S`` and of the ``BEFORE_S`` before them, the two errors differ by the iron's move; where they
differ by more than ``MOVED_UT`` and by ``SIGMAS`` of their uncertainty (the residual's spread over the windows,
counted as one window in ``WINDOW_SPACING``), the iron moved. Constant errors of the estimate (the gyroscope's bias,
the record's own soft iron) are the same in both and cancel. An object passed on the way (a steel door) bends a few
windows, which the residual's spread counts.

``IronWatch`` keeps, per device, the fit's sums (normal equations) in blocks of ``BLOCK_S`` of samples, each block's
windows computed once from its own samples and the second before: memory a few numbers a block, CPU the new samples
only. Pure numpy.
"""

from __future__ import annotations

import numpy as np

from magnet.calibration.gyro_ellipsoid import gyro_attitudes, windows
from magnet.frames import rotation_vector_to_matrix

#: the recent stretch (s) and the stretch before it it is compared with (s), in blocks of BLOCK_S
RECENT_S = 8.0
BEFORE_S = 20.0
BLOCK_S = 2.0
#: the windows: each ends where the gyroscope turned this much (deg), within this long (s), at least this much (deg)
WINDOW_DEG, WINDOW_S, LEAST_DEG = 45.0, 1.0, 20.0
#: windows start this often (s); windows closer than WINDOW_S share samples and count as WINDOW_S / this of one
WINDOW_SPACING_S = 0.25
#: a move is this large at least (uT) ...
MOVED_UT = 2.0
#: ... and its chi-square over its covariance this large (3 degrees of freedom: 1 in 10^4 by chance)
CHI2 = 21.0
#: fewest windows in each stretch
MIN_WINDOWS = 8


def block_sums(field_ut: np.ndarray, gyr_rads: np.ndarray, period_s: float, first: int) -> np.ndarray:
    """The fit's sums (13,) over the windows that start at sample ``first`` or later: D^T D (9), D^T y (3), y^T y,
    and their count last is left to the caller: (14,) with it. field (N, 3) uT corrected by the record, rates
    (N, 3) rad/s, every ``period_s`` s; D = P^T - I, y = P^T B(s) - B(e) per window (module docstring)."""
    every = max(1, round(WINDOW_SPACING_S / period_s))
    starts, ends = windows(gyr_rads, period_s, WINDOW_DEG, WINDOW_S, LEAST_DEG, every)
    keep = starts >= first
    starts, ends = starts[keep], ends[keep]
    out = np.zeros(14)
    if not len(starts):
        return out
    attitudes = gyro_attitudes(rotation_vector_to_matrix(gyr_rads * period_s))
    back = np.transpose(attitudes[ends], (0, 2, 1)) @ attitudes[starts]  # P^T
    design = (back - np.eye(3)).reshape(-1, 3)
    target = (np.einsum("nij,nj->ni", back, field_ut[starts]) - field_ut[ends]).reshape(-1)
    out[:9] = (design.T @ design).ravel()
    out[9:12] = design.T @ target
    out[12] = target @ target
    out[13] = len(starts)
    return out


def offset_error(sums: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
    """(the offset error d (3,) uT, its covariance (3, 3) uT^2) from a stretch's ``block_sums`` added up; None with
    fewer than ``MIN_WINDOWS`` windows or turns about fewer than two axes."""
    if sums[13] < MIN_WINDOWS:
        return None
    normal = sums[:9].reshape(3, 3)
    if np.linalg.cond(normal) > 1e6:
        return None
    inverse = np.linalg.inv(normal)
    error = inverse @ sums[9:12]
    residual = max(float(sums[12] - error @ sums[9:12]), 0.0)  # y^T y - d^T D^T y at the solution
    variance = residual / max(3.0 * sums[13] - 3.0, 1.0)
    overlap = max(1.0, WINDOW_S / WINDOW_SPACING_S)
    return error, inverse * variance * overlap


def change(recent: np.ndarray, before: np.ndarray) -> tuple[float, float] | None:
    """(how far (uT) the offset error of the ``recent`` stretch's sums lies from the ``before`` one's, and that
    difference's chi-square over its covariance); None where either is unknown."""
    now, then = offset_error(recent), offset_error(before)
    if now is None or then is None:
        return None
    difference = now[0] - then[0]
    return float(np.linalg.norm(difference)), float(difference @ np.linalg.solve(now[1] + then[1], difference))


class IronWatch:
    """One device's blocks of sums (``block_sums``) under the record in force: ``add`` a run's new samples, True
    when the iron moved (``MOVED_UT`` and ``CHI2`` between the last ``RECENT_S`` and the ``BEFORE_S`` before)."""

    def __init__(self) -> None:
        self.blocks: list[np.ndarray] = []
        self.done_ns: int | None = None  # the newest sample already in a block

    def add(self, field_ut: np.ndarray, gyr_rads: np.ndarray, t_ns: np.ndarray, period_s: float) -> bool:
        """The run's samples (field (N, 3) corrected by the record, rates (N, 3), times (N,) ns, consecutive):
        once ``BLOCK_S`` of them are new, a block is made of them (its windows may reach back ``WINDOW_S``)."""
        first = 0 if self.done_ns is None else int(np.searchsorted(t_ns, self.done_ns, side="right"))
        if (len(t_ns) - first) * period_s < BLOCK_S:
            return False
        back = max(0, first - round(WINDOW_S / period_s) - 1)
        self.blocks.append(block_sums(field_ut[back:], gyr_rads[back:], period_s, first - back))
        self.done_ns = int(t_ns[-1])
        recent, before = round(RECENT_S / BLOCK_S), round(BEFORE_S / BLOCK_S)
        del self.blocks[: max(0, len(self.blocks) - recent - before)]
        if len(self.blocks) < recent + before // 2:
            return False
        sums = np.array(self.blocks)
        found = change(sums[-recent:].sum(axis=0), sums[:-recent].sum(axis=0))
        return found is not None and found[0] > MOVED_UT and found[1] > CHI2
