"""A recording played back at its own pace: the pure part of ``magnet edge --replay FILE.csv``.

A ``Recording`` holds what ``magnet sample`` writes: sample times ``t_s`` and the field, with the accelerometer and
gyroscope when recorded. ``paced_slices`` cuts it into batches and releases each one when its last sample's time has
come (the recording's time divided by ``speed``, counted from the first call); ``stamps_ns`` gives the samples' wire
times: the recording's own intervals (never scaled, so a gyroscope's rates still integrate to the recorded angles)
from an anchor such as the wall clock at the start. Clock and sleep are injected.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Iterator

import numpy as np

from magnet.wire import MAX_ACC_MS2, MAX_FIELD_UT, MAX_GYR_RADS
from magnet.wire.raw import MAX_VEL_MS

MAX_SPEED = 1000.0
#: the longest single sleep, so that a stop request is seen within this many seconds even across a gap
MAX_SLEEP_S = 0.5


def _check_vectors(name: str, values: np.ndarray | None, n: int, limit: float) -> None:
    if values is None:
        return
    if values.shape != (n, 3):
        raise ValueError(f"{name} must have shape ({n}, 3), got {values.shape}")
    bad = ~np.isfinite(values).all(axis=1) | (np.abs(values) > limit).any(axis=1)
    if bad.any():
        row = int(np.argmax(bad))
        raise ValueError(f"{name} row {row + 1} is not finite or beyond +-{limit:g}: {values[row].tolist()}")


@dataclasses.dataclass(frozen=True, eq=False)
class Recording:
    """N recorded samples. t_s (N,) seconds, finite, never decreasing; mag_ut (N, 3) uT body frame; acc_ms2 (N, 3)
    m/s^2 or None; gyr_rads (N, 3) rad/s body frame or None; vel_ned_ms (N, 3) m/s NED or None (NaN rows where
    unknown). Values within the wire's limits."""

    t_s: np.ndarray
    mag_ut: np.ndarray
    acc_ms2: np.ndarray | None = None
    gyr_rads: np.ndarray | None = None
    vel_ned_ms: np.ndarray | None = None

    def __post_init__(self) -> None:
        if self.t_s.ndim != 1 or self.t_s.size == 0:
            raise ValueError(f"a recording needs at least one sample time, got shape {self.t_s.shape}")
        if not np.isfinite(self.t_s).all():
            raise ValueError("the sample times t_s must be finite")
        steps = np.diff(self.t_s)
        if (steps < 0).any():
            row = int(np.argmax(steps < 0)) + 2
            raise ValueError(
                f"the sample times t_s go backwards at row {row}: {self.t_s[row - 2]} then {self.t_s[row - 1]}"
            )
        n = self.t_s.size
        _check_vectors("mag_ut", self.mag_ut, n, MAX_FIELD_UT)
        _check_vectors("acc_ms2", self.acc_ms2, n, MAX_ACC_MS2)
        _check_vectors("gyr_rads", self.gyr_rads, n, MAX_GYR_RADS)
        if self.vel_ned_ms is not None:  # NaN rows allowed: no fix yet
            known = self.vel_ned_ms[np.isfinite(self.vel_ned_ms).all(axis=1)] if self.vel_ned_ms.ndim == 2 else None
            _check_vectors("vel_ned_ms", known, len(known) if known is not None else n, MAX_VEL_MS)

    def __len__(self) -> int:
        return int(self.t_s.size)

    def stamps_ns(self, anchor_ns: int) -> np.ndarray:
        """(N,) int64 ns: the first sample at ``anchor_ns``, the others at the recording's intervals after it."""
        return anchor_ns + np.round((self.t_s - self.t_s[0]) * 1e9).astype(np.int64)


def _sleep_until(
    target: float, clock: Callable[[], float], sleep: Callable[[float], None], stop: Callable[[], bool]
) -> bool:
    """Sleep until ``clock() >= target`` in steps of at most MAX_SLEEP_S; False if ``stop()`` turned true first."""
    while not stop():
        delay = target - clock()
        if delay <= 0:
            return True
        sleep(min(delay, MAX_SLEEP_S))
    return False


def paced_slices(
    recording: Recording,
    batch: int,
    *,
    speed: float,
    clock: Callable[[], float],
    sleep: Callable[[float], None],
    stop: Callable[[], bool] = lambda: False,
) -> Iterator[slice]:
    """Slices of at most ``batch`` samples, each yielded once its last sample is due: at ``start + (t_s[last] -
    t_s[0]) / speed`` on ``clock`` (seconds), ``start`` being the clock at the first call. Ends early on ``stop()``."""
    if batch < 1:
        raise ValueError(f"batch must be >= 1, got {batch}")
    if not 0 < speed <= MAX_SPEED:
        raise ValueError(f"--speed must be in (0, {MAX_SPEED:g}], got {speed}")
    due_s = (recording.t_s - recording.t_s[0]) / speed
    start = clock()
    for lo in range(0, len(recording), batch):
        hi = min(lo + batch, len(recording))
        if not _sleep_until(start + due_s[hi - 1], clock, sleep, stop):
            return
        yield slice(lo, hi)
