"""The recent samples of one device in time order, with its gyroscope: what a fit from the gyroscope
(``gyro-ellipsoid``) needs, which the sphere cells of ``magnet.calibration.collection`` (one sample per direction, no
order) lose.

A bounded ring of the last ``capacity`` samples; the samples are cut into *runs* of consecutive readings: a run
restarts where a batch's ``seq`` is not the previous one's plus one (a batch lost, or the edge restarted), or where
two consecutive ``t_ns`` are not increasing or lie more than ``GAP_PERIODS`` sample periods apart (a stall: more than
``MOST_MISSING`` samples lost, whose rotation is unknown, or the device stopped). The fit never pairs samples across a
restart: it is given the longest run (the most recent among equals). Within a run a phone drops samples (a busy
sensor hub: 2 % of them); the sample after k missing ones is taken over its k + 1 periods (``Run.periods``), as the
compass does (``magnet.compass.missed``), so that the gyroscope's rotation over the run is the device's.

Memory per device: ``capacity`` rows of 14 numbers of 8 bytes (mag, acc, gyr and velocity 3 each, t_ns, run number):
112 bytes a sample, 3.4 MB for the default 30,000 (5 minutes at 100 Hz); the arrays start at ``INITIAL_ROOM`` rows
and double, so a device that sends little costs little. Pure numpy.
"""

from __future__ import annotations

import dataclasses

import numpy as np

#: samples held per device by default: 5 minutes at 100 Hz (2.6 MB)
RUN_CAPACITY = 30_000
#: missing samples in a row bridged within a run, as the compass makes them up (``magnet.compass.missed``): the rate
#: after them is taken as theirs; over a longer stall (a busy phone: 0.2-0.5 s) the rotation is unknown: a new run
MOST_MISSING = 3
#: a stream whose steps look like gaps more often than this is not one that drops samples: its period is misread
MOST_GAPS = 0.25
#: a step between consecutive t_ns longer than this many sample periods starts a new run
GAP_PERIODS = MOST_MISSING + 1.5
#: rates below this about an axis (rad/s, 6 deg/s) are not counted as turning about it (noise, bias)
TURNING_RADS = 0.1
INITIAL_ROOM = 256


@dataclasses.dataclass(frozen=True)
class Run:
    """Consecutive samples of one device: mag (N, 3) uT, acc (N, 3) m/s^2 or None (a sample came without),
    gyr_rads (N, 3) rad/s, t_ns (N,) int64, period_s, the median step of t_ns in seconds, vel_ned_ms (N, 3) m/s
    geographic NED, the velocity the batches carried (NaN rows where none), or None when no sample had one, and
    periods (N,) float, the whole periods each sample's step spans (k + 1 after k missing samples; the first 1), or
    None where none is missing."""

    mag: np.ndarray
    acc: np.ndarray | None
    gyr_rads: np.ndarray
    t_ns: np.ndarray
    period_s: float
    vel_ned_ms: np.ndarray | None = None
    periods: np.ndarray | None = None

    def __len__(self) -> int:
        return len(self.mag)

    @property
    def turn_rads(self) -> np.ndarray:
        """(N, 3) rad/s: the rates to integrate at one ``period_s`` a sample: ``gyr_rads``, each sample after k
        missing ones k + 1 times (the rate after a gap is the best estimate of the rate over it)."""
        return self.gyr_rads if self.periods is None else self.gyr_rads * self.periods[:, None]

    def tail(self, seconds: float) -> Run:
        """The last ``seconds`` of the run (all of it when shorter)."""
        count = max(2, round(seconds / self.period_s)) if self.period_s > 0 else len(self)
        if count >= len(self):
            return self
        acc = None if self.acc is None else self.acc[-count:]
        vel = None if self.vel_ned_ms is None else self.vel_ned_ms[-count:]
        periods = None if self.periods is None else self.periods[-count:]
        return Run(self.mag[-count:], acc, self.gyr_rads[-count:], self.t_ns[-count:], self.period_s, vel, periods)

    def turned_deg(self) -> np.ndarray:
        """(3,) how far the device turned about each body axis, deg: |rate| summed over the samples where it
        exceeds ``TURNING_RADS`` about that axis (so a gyroscope's noise and bias do not add up), over each sample's
        whole periods."""
        rates = np.abs(self.gyr_rads)
        turning = np.where(rates > TURNING_RADS, rates, 0.0)
        if self.periods is not None:
            turning = turning * self.periods[:, None]
        return np.degrees(turning.sum(axis=0) * self.period_s)


class RecentRuns:
    """The last ``capacity`` samples of one device (mag, acc, gyr, t_ns) in a ring, each tagged with its run."""

    def __init__(self, capacity: int = RUN_CAPACITY) -> None:
        if capacity < 2:
            raise ValueError(f"a run ring needs room for at least 2 samples, got {capacity}")
        self.capacity = capacity
        rows = min(capacity, INITIAL_ROOM)
        self.mag, self.acc, self.gyr = np.empty((rows, 3)), np.empty((rows, 3)), np.empty((rows, 3))
        self.vel = np.empty((rows, 3))
        self.t_ns, self.run = np.empty(rows, dtype=np.int64), np.empty(rows, dtype=np.int64)
        self.head = self.held = self.written = 0  # next row to write; rows holding samples; samples ever written
        self.run_no = 0
        self.last_seq: int | None = None
        self.last_t_ns: int | None = None
        self.period_ns: float | None = None

    def add(
        self,
        mag: np.ndarray,
        acc: np.ndarray | None,
        gyr_rads: np.ndarray,
        t_ns: np.ndarray,
        seq: int,
        vel_ned_ms: np.ndarray | None = None,
    ) -> None:
        """Append one batch: mag, gyr_rads (N, 3), acc (N, 3) or None, t_ns (N,) int ns, ``seq`` the batch's number,
        vel_ned_ms (N, 3) m/s or None (kept as NaN rows)."""
        t = np.asarray(t_ns, dtype=np.int64)
        if not len(t):
            return
        steps = np.diff(t)
        if (steps > 0).any():
            self.period_ns = float(np.median(steps[steps > 0]))
        starts = np.zeros(len(t), dtype=bool)
        starts[0] = self._restarts(int(t[0]), seq)
        if self.period_ns is not None:
            starts[1:] = (steps <= 0) | (steps > GAP_PERIODS * self.period_ns)
        runs = self.run_no + np.cumsum(starts)
        self.run_no, self.last_seq, self.last_t_ns = int(runs[-1]), seq, int(t[-1])
        acc_rows = np.full((len(t), 3), np.nan) if acc is None else acc
        vel_rows = np.full((len(t), 3), np.nan) if vel_ned_ms is None else vel_ned_ms
        self._write(mag, acc_rows, gyr_rads, t, runs, vel_rows)

    def _restarts(self, first_t_ns: int, seq: int) -> bool:
        """Whether a batch starting at ``first_t_ns`` with number ``seq`` cannot follow the last one."""
        if self.last_seq is None or self.last_t_ns is None or seq != self.last_seq + 1:
            return True
        step = first_t_ns - self.last_t_ns
        return step <= 0 or (self.period_ns is not None and step > GAP_PERIODS * self.period_ns)

    def _write(
        self, mag: np.ndarray, acc: np.ndarray, gyr: np.ndarray, t: np.ndarray, runs: np.ndarray, vel: np.ndarray
    ) -> None:
        keep = slice(max(0, len(t) - self.capacity), len(t))  # a batch longer than the ring: its newest samples
        count = len(t[keep])
        self._room_for(self.held + count)
        rows = (self.head + np.arange(count)) % len(self.mag)
        self.mag[rows], self.acc[rows], self.gyr[rows] = mag[keep], acc[keep], gyr[keep]
        self.vel[rows] = vel[keep]
        self.t_ns[rows], self.run[rows] = t[keep], runs[keep]
        self.head = int((self.head + count) % len(self.mag))
        self.held = min(self.held + count, len(self.mag))
        self.written += len(t)

    def _room_for(self, size: int) -> None:
        """Grow the arrays (doubling, at most to the capacity) while the ring has not wrapped yet."""
        rows = len(self.mag)
        if size <= rows or rows >= self.capacity:
            return
        grow = min(self.capacity, max(size, 2 * rows)) - rows
        vectors, times = np.empty((grow, 3)), np.empty(grow, dtype=np.int64)
        self.mag, self.acc, self.gyr, self.vel = (
            np.concatenate([a, vectors]) for a in (self.mag, self.acc, self.gyr, self.vel)
        )
        self.t_ns, self.run = (np.concatenate([a, times]) for a in (self.t_ns, self.run))
        self.head = self.held  # not wrapped: the samples are rows 0 .. held - 1

    def longest(self) -> Run | None:
        """The longest run held (the most recent of equals), None when no run has two samples."""
        order = np.arange(self.held) if self.held < len(self.mag) else (self.head + np.arange(self.held)) % self.held
        runs = self.run[order]  # non-decreasing in time order: each run is one stretch
        first = np.concatenate([[0], np.flatnonzero(np.diff(runs)) + 1])
        counts = np.diff(np.concatenate([first, [len(runs)]]))
        if not len(counts) or counts.max() < 2:
            return None
        best = len(counts) - 1 - int(np.argmax(counts[::-1]))
        rows = order[first[best] : first[best] + counts[best]]
        acc, vel = self.acc[rows], self.vel[rows]
        t = self.t_ns[rows]
        period_ns = float(np.median(np.diff(t)))
        return Run(
            self.mag[rows],
            None if np.isnan(acc).any() else acc,
            self.gyr[rows],
            t,
            period_ns / 1e9,
            vel if np.isfinite(vel).all(axis=1).any() else None,
            whole_periods(t, period_ns),
        )


def whole_periods(t_ns: np.ndarray, period_ns: float) -> np.ndarray | None:
    """(N,) the whole periods of ``period_ns`` each sample's step from the one before spans (t_ns (N,) int ns in
    time order; the first sample 1), rounded, at least 1 and at most ``MOST_MISSING`` + 1; None where every step is
    one period (a stream without missing samples is integrated as before, to the bit). Time stamps' jitter moves a
    step by a fraction and is not a gap. Stamps far from a regular stream (a step under half a period, or more than
    ``MOST_GAPS`` of the steps looking like gaps: a flight log's come in pairs a fraction of a period apart, and its
    median step is then the short one) are left as they come: None."""
    if len(t_ns) < 2 or not period_ns > 0.0:
        return None
    ratio = np.diff(np.asarray(t_ns, dtype=np.int64)).astype(float) / period_ns
    if ratio.min() < 0.5:
        return None
    periods = np.clip(np.rint(ratio), 1.0, MOST_MISSING + 1.0)
    gaps = periods > 1.0
    if not gaps.any() or gaps.mean() > MOST_GAPS:
        return None
    return np.concatenate([[1.0], periods])
