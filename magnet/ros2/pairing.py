"""A ROS 2 robot's MagneticField and Imu streams joined into magnet's raw samples (pure; the clock is passed in).

Each MagneticField sample waits for the Imu sample of its time: it is released as soon as an Imu stamped at or after
it has arrived (or at once without an Imu topic, or after ``wait_s`` with none) and takes the Imu sample nearest in
time within ``tolerance_ns``. Released samples are converted to magnet's frame (``magnet.ros2.frames.from_ros``) and
cut into batches: ``batch`` samples, or fewer once the oldest has waited ``flush_s``; a batch holds acceleration
(and rates) only when all its samples have them, so a run with and without is cut where that changes.

A MagneticField stamped at or before the last one taken (a stamp that runs backwards) is dropped and counted
(``mag-backwards``): the wire's times only go forward, and publishing it would hide a robot whose clock jumps.
"""

from __future__ import annotations

import bisect
import dataclasses
from collections import deque

import numpy as np

from magnet.ros2.frames import from_ros
from magnet.ros2.messages import ImuSample, MagSample

__all__ = ["Joined", "SamplePairer"]

#: samples held at most in each of the two buffers (a stalled Imu topic cannot grow memory without bound). Not
#: ``magnet.bounded.Recent``: that is a map keyed by device, ordered by when a key was last seen, that forgets its
#: least recent key. These buffers have no keys: the field samples are a queue in arrival order taken from the front,
#: the Imu samples a list kept sorted by stamp (they may come out of order) and searched by bisection for the nearest
#: one; each is cut from its front as samples are used, and a sample beyond the bound is refused and counted.
MAX_PENDING = 100_000
#: ... and bytes held at most in each buffer: a sample counts ``SAMPLE_BYTES`` (its Python objects: the sample, its
#: arrays, its list entry) plus its frame id's length. A count alone let 100 kB frame ids make 334 MB of Imu samples.
MAX_PENDING_BYTES = 16 * 1024 * 1024
SAMPLE_BYTES = 400


def sample_bytes(sample: MagSample | ImuSample) -> int:
    """What a buffered sample is counted as holding (bytes)."""
    return SAMPLE_BYTES + len(sample.frame_id)


@dataclasses.dataclass(frozen=True, eq=False)
class Joined:
    """One batch in magnet's frames: t_ns (n,), mag_ut (n, 3) FRD uT, acc_ms2 and gyr_rads (n, 3) FRD or None."""

    t_ns: np.ndarray
    mag_ut: np.ndarray
    acc_ms2: np.ndarray | None
    gyr_rads: np.ndarray | None


class SamplePairer:
    """MagneticField samples paired with Imu samples by time; ``dropped`` counts samples let go by cause."""

    def __init__(
        self, with_imu: bool, batch: int, tolerance_ns: int = 20_000_000, wait_s: float = 0.2, flush_s: float = 0.25
    ) -> None:
        self.with_imu, self.batch = with_imu, batch
        self.tolerance_ns, self.wait_s, self.flush_s = tolerance_ns, wait_s, flush_s
        self.pending: deque[tuple[float, MagSample]] = deque()
        self.imu_t: list[int] = []
        self.imu: list[ImuSample] = []
        self.released: list[tuple[float, MagSample, ImuSample | None]] = []
        self.dropped: dict[str, int] = {}
        #: bytes held (``sample_bytes``) by the field samples not yet batched, and by the Imu samples
        self.mag_bytes = self.imu_bytes = 0
        self.last_mag_ns: int | None = None

    def _drop(self, cause: str) -> None:
        self.dropped[cause] = self.dropped.get(cause, 0) + 1

    def add_mag(self, sample: MagSample, now_s: float) -> None:
        size = sample_bytes(sample)
        if len(self.pending) >= MAX_PENDING or self.mag_bytes + size > MAX_PENDING_BYTES:
            self._drop("mag-backlog")
            return
        if self.last_mag_ns is not None and sample.t_ns <= self.last_mag_ns:
            self._drop("mag-backwards")
            return
        self.last_mag_ns = sample.t_ns
        self.mag_bytes += size
        self.pending.append((now_s, sample))

    def add_imu(self, sample: ImuSample) -> None:
        if not self.with_imu:
            return
        size = sample_bytes(sample)
        if len(self.imu) >= MAX_PENDING or self.imu_bytes + size > MAX_PENDING_BYTES:
            self._drop("imu-backlog")
            return
        at = bisect.bisect_right(self.imu_t, sample.t_ns)
        self.imu_t.insert(at, sample.t_ns)
        self.imu.insert(at, sample)
        self.imu_bytes += size

    def _nearest_imu(self, t_ns: int) -> ImuSample | None:
        at = bisect.bisect_left(self.imu_t, t_ns)
        best = min(
            (i for i in (at - 1, at) if 0 <= i < len(self.imu_t)),
            key=lambda i: abs(self.imu_t[i] - t_ns),
            default=None,
        )
        if best is None or abs(self.imu_t[best] - t_ns) > self.tolerance_ns:
            return None
        return self.imu[best]

    def _release(self, now_s: float) -> None:
        while self.pending:
            arrived, mag = self.pending[0]
            covered = bool(self.imu_t) and self.imu_t[-1] >= mag.t_ns
            if self.with_imu and not covered and now_s - arrived < self.wait_s:
                break
            self.pending.popleft()
            self.released.append((arrived, mag, self._nearest_imu(mag.t_ns) if self.with_imu else None))
        if self.pending and self.imu_t:  # Imu samples too old to pair with anything still waiting
            keep = bisect.bisect_left(self.imu_t, self.pending[0][1].t_ns - self.tolerance_ns)
            self.imu_bytes -= sum(map(sample_bytes, self.imu[:keep]))
            del self.imu_t[:keep], self.imu[:keep]

    def batches(self, now_s: float, flush: bool = False) -> list[Joined]:
        """The batches ready at ``now_s`` (all that is released, with ``flush``)."""
        self._release(now_s)
        out = []
        while self.released and (
            len(self.released) >= self.batch or flush or now_s - self.released[0][0] >= self.flush_s
        ):
            run = self._run()
            out.append(_joined(run))
        return out

    def _run(self) -> list[tuple[float, MagSample, ImuSample | None]]:
        """The next samples up to ``batch`` whose having an Imu sample is the same, taken from ``released``."""
        has = [imu is not None and imu.acc_ms2 is not None for _, _, imu in self.released[: self.batch]]
        size = next((i for i, h in enumerate(has) if h != has[0]), len(has))
        run, self.released = self.released[:size], self.released[size:]
        self.mag_bytes -= sum(sample_bytes(mag) for _, mag, _ in run)
        return run


def _joined(run: list[tuple[float, MagSample, ImuSample | None]]) -> Joined:
    t_ns = np.array([mag.t_ns for _, mag, _ in run], dtype=np.int64)
    field_t = np.array([mag.field_t for _, mag, _ in run])
    accs = [None if imu is None else imu.acc_ms2 for _, _, imu in run]
    gyrs = [None if imu is None else imu.gyr_rads for _, _, imu in run]
    acc = None if any(a is None for a in accs) else np.array(accs, dtype=float)
    gyr = None if acc is None or any(g is None for g in gyrs) else np.array(gyrs, dtype=float)
    mag_ut, acc_frd, gyr_frd = from_ros(field_t, acc if acc is not None else np.zeros_like(field_t), gyr)
    return Joined(t_ns, mag_ut, acc_frd if acc is not None else None, gyr_frd)
