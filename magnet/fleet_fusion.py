"""One gyroscope-aided filter per device for the live compass (DESIGN.md 4b): state kept across batches.

The compass decodes a drain of raw batches of many devices, computes accelerometer-tilt headings for every sample
(``magnet.compass.compute_headings``) and then hands the batches that carry a gyroscope to ``FleetFusion.update``,
which runs each device's ``magnet.fusion.Fusion`` on them, batch after batch, and ``merge`` puts the fused attitude in
place of the tilt one. Per device:

- the filter runs at the device's sample period (median step of the batch's ``t_ns``); a period that changes by more
  than ``PERIOD_TOLERANCE`` gets a new filter;
- continuity: a batch whose ``seq`` does not follow the last one (lower or equal: the device restarted, or replays)
  or whose first sample comes more than ``MAX_GAP_S`` after the last one (lost batches, a pause) restarts the filter:
  the rotation over a gap is unknown, and a restarted filter takes its tilt from gravity at once and its heading from
  the field within seconds, where integrating across the gap would carry an error for tens of seconds;
- bad gyroscope samples are dropped and counted: non-finite ones are skipped (the filter goes on: one missing sample
  is a short gap); saturated or absurd ones (a component at or beyond ``GYRO_LIMIT_RADS``) are skipped and restart
  the filter after them, since the rotation while saturated is unknown. Samples without a finite accelerometer or
  field reading are not fused either. Samples not fused keep the tilt heading (flag FUSED clear): never NaN.
- magnetic disturbance: vqf's detection (|B| or dip away from its reference) sets FIELD_DISTURBED, and vqf then
  leaves the field out of the heading, so a disturbance does not drag it; the compass judges the dip of fused
  samples against the fused gravity (``FusedColumns.gravity``), not the accelerometer.

State is bounded: at most ``MAX_DEVICES`` filters, the least recently used forgotten first.
"""

from __future__ import annotations

import dataclasses
from collections import OrderedDict
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

from magnet import fusion
from magnet import heading as hd
from magnet.attitude import matrix_to_euler, quaternion_to_matrix
from magnet.compass import Headings

#: 2000 deg/s, the widest full scale of common MEMS gyroscopes (ICM-20948, LSM9DS1, MPU-6050): a reading at or beyond
#: it is saturated, and the rotation while it lasts is unknown
GYRO_LIMIT_RADS = np.radians(2000.0) * 0.999
#: a gap in time longer than this (seconds) restarts a device's filter
MAX_GAP_S = 0.5
#: relative change of the sample period beyond which a device gets a new filter
PERIOD_TOLERANCE = 0.1
MAX_DEVICES = 100_000


@dataclasses.dataclass(frozen=True, eq=False)
class FusedColumns:
    """Fused attitude for S samples of many batches. fused (S,) bool where the filter ran; quat_wxyz (S, 4) body ->
    magnetic NED, heading_deg / pitch_deg / roll_deg (S,) and down (S, 3) (NED down in body axes): NaN where not
    fused; mag_disturbed (S,) bool. dropped: gyroscope samples dropped by cause; restarts: filters restarted."""

    fused: np.ndarray
    quat_wxyz: np.ndarray
    heading_deg: np.ndarray
    pitch_deg: np.ndarray
    roll_deg: np.ndarray
    down: np.ndarray
    mag_disturbed: np.ndarray
    dropped: Mapping[str, int]
    restarts: int

    @classmethod
    def empty(cls, count: int) -> FusedColumns:
        nan = np.full(count, np.nan)
        return cls(
            np.zeros(count, bool),
            np.full((count, 4), np.nan),
            nan,
            nan.copy(),
            nan.copy(),
            np.full((count, 3), np.nan),
            np.zeros(count, bool),
            {},
            0,
        )

    def gravity(self, acc_ms2: np.ndarray) -> np.ndarray:
        """Specific force (S, 3) as a still device would read it: -down (unit) where fused, else ``acc_ms2``."""
        return np.where(self.fused[:, None], -self.down, acc_ms2)

    @classmethod
    def from_vqf(
        cls, raw: np.ndarray, disturbed: np.ndarray, dropped: Mapping[str, int], restarts: int
    ) -> FusedColumns:
        """From vqf's quaternions (S, 4) (NaN rows where not fused), converted to the project's frames at once."""
        out = cls.empty(len(raw))
        fused = np.isfinite(raw).all(axis=1)
        if fused.any():
            quat = fusion.vqf_to_body_ned(raw[fused])
            matrix = quaternion_to_matrix(quat)
            heading, pitch, roll = matrix_to_euler(matrix)
            out.quat_wxyz[fused], out.down[fused] = quat, matrix[:, 2, :]
            out.heading_deg[fused], out.pitch_deg[fused], out.roll_deg[fused] = heading, pitch, roll
        return dataclasses.replace(
            out, fused=fused, mag_disturbed=disturbed & fused, dropped=dict(dropped), restarts=restarts
        )


class DeviceFusion:
    """The filter of one device and what it needs to judge continuity (last seq, last time, period)."""

    def __init__(self, params: Mapping[str, Any] | None = None, max_gap_s: float = MAX_GAP_S) -> None:
        self.params = dict(params or {})
        self.max_gap_s = max_gap_s
        self.filter: fusion.Fusion | None = None
        self.last_seq: int | None = None
        self.last_t_ns: int | None = None
        self.restarts = 0

    def _period_s(self, t_ns: np.ndarray) -> float | None:
        """Mean step of the batch's times (or from the last sample for a batch of one); None when unusable."""
        if len(t_ns) >= 2:
            period = (int(t_ns[-1]) - int(t_ns[0])) * 1e-9 / (len(t_ns) - 1)
        elif self.last_t_ns is not None:
            period = (int(t_ns[0]) - self.last_t_ns) * 1e-9
        else:
            return None
        return period if fusion.MIN_PERIOD_S <= period <= fusion.MAX_PERIOD_S else None

    def _continues(self, seq: int, t_ns: np.ndarray, period_s: float) -> bool:
        if self.filter is None or self.last_seq is None or self.last_t_ns is None:
            return False
        step_s = (int(t_ns[0]) - self.last_t_ns) * 1e-9
        same_rate = abs(self.filter.period_s - period_s) <= PERIOD_TOLERANCE * period_s
        return seq > self.last_seq and 0 < step_s <= self.max_gap_s + period_s and same_rate

    def update(
        self,
        seq: int,
        t_ns: np.ndarray,
        vqf_inputs: tuple[np.ndarray, np.ndarray, np.ndarray],
        usable: np.ndarray,
        saturated: np.ndarray,
        out: np.ndarray,
        disturbed: np.ndarray,
    ) -> None:
        """Fuse one batch of N samples: t_ns (N,) int ns; vqf_inputs gyroscope, accelerometer and field (N, 3) each,
        already in vqf's frame (``fusion.to_vqf_frame``); usable and saturated (N,) bool. Writes vqf's quaternions
        into ``out`` (N, 4) and its disturbance flags into ``disturbed`` (N,) for the samples it fused."""
        period = self._period_s(t_ns)
        if period is None or (len(t_ns) > 1 and not (np.diff(t_ns) > 0).all()):
            self.filter, self.last_seq, self.last_t_ns = None, seq, int(t_ns[-1])
            return
        if not self._continues(seq, t_ns, period):
            self._restart(period)
        if saturated.any():
            start = 0
            for stop in [*np.flatnonzero(saturated).tolist(), len(t_ns)]:
                self._run(vqf_inputs, np.arange(start, stop)[usable[start:stop]], out, disturbed)
                if stop < len(t_ns):
                    self._restart(period)
                start = stop + 1
        else:
            self._run(vqf_inputs, slice(None) if usable.all() else np.flatnonzero(usable), out, disturbed)
        self.last_seq, self.last_t_ns = seq, int(t_ns[-1])

    def _restart(self, period_s: float) -> None:
        if self.filter is not None and abs(self.filter.period_s - period_s) <= PERIOD_TOLERANCE * period_s:
            self.filter.restart()
        else:
            self.filter = fusion.Fusion(period_s, self.params)
        self.restarts += 1

    def _run(
        self, vqf_inputs: tuple[np.ndarray, np.ndarray, np.ndarray], rows: Any, out: np.ndarray, disturbed: np.ndarray
    ) -> None:
        if self.filter is None or (isinstance(rows, np.ndarray) and rows.size == 0):
            return
        gyr, acc, field = (np.ascontiguousarray(x[rows]) for x in vqf_inputs)
        out[rows], disturbed[rows] = self.filter.update_vqf_frame(gyr, acc, field)


class FleetFusion:
    """One ``DeviceFusion`` per device, at most ``max_devices`` (least recently used forgotten first)."""

    def __init__(
        self, params: Mapping[str, Any] | None = None, max_gap_s: float = MAX_GAP_S, max_devices: int = MAX_DEVICES
    ) -> None:
        self.params, self.max_gap_s, self.max_devices = dict(params or {}), max_gap_s, max_devices
        self.devices: OrderedDict[str, DeviceFusion] = OrderedDict()
        self.evicted = 0  # filters forgotten for the max_devices bound

    def _device(self, name: str) -> DeviceFusion:
        state = self.devices.get(name)
        if state is None:
            state = self.devices[name] = DeviceFusion(self.params, self.max_gap_s)
            while len(self.devices) > self.max_devices:
                self.devices.popitem(last=False)
                self.evicted += 1
        else:
            self.devices.move_to_end(name)
        return state

    def update(
        self,
        devices: Sequence[str],
        seqs: Sequence[int],
        bounds: Sequence[int],
        t_ns: np.ndarray,
        gyr_rads: np.ndarray,
        acc_ms2: np.ndarray,
        field_ut: np.ndarray,
    ) -> FusedColumns:
        """Fuse every batch b (samples bounds[b] .. bounds[b+1]) that carries a gyroscope (not all-NaN rows), in
        order; S = bounds[-1] samples, arrays (S, 3). Checks and frame conversions are done once for all samples,
        the filters run batch by batch."""
        count = int(bounds[-1])
        edges = np.asarray(bounds, dtype=np.int64)
        sizes = np.diff(edges)
        present = ~np.isnan(gyr_rads).all(axis=1)
        if not present.any():
            return FusedColumns.empty(count)
        with_gyro = np.zeros(len(sizes), dtype=bool)
        nonempty = sizes > 0
        with_gyro[nonempty] = np.logical_or.reduceat(present, edges[:-1][nonempty])
        gyro_rows = np.repeat(with_gyro, sizes)  # every sample of a batch that carries a gyroscope
        finite = np.isfinite(gyr_rads).all(axis=1)
        saturated = finite & (np.abs(gyr_rads) >= GYRO_LIMIT_RADS).any(axis=1)
        usable = finite & ~saturated & np.isfinite(acc_ms2).all(axis=1) & np.isfinite(field_ut).all(axis=1)
        gyr, acc, field = (
            fusion.to_vqf_frame(np.where(usable[:, None], x, 0.0)) for x in (gyr_rads, acc_ms2, field_ut)
        )
        raw = np.full((count, 4), np.nan)
        disturbed = np.zeros(count, dtype=bool)
        restarts = 0
        for b, device in enumerate(devices):
            lo, hi = int(bounds[b]), int(bounds[b + 1])
            if not with_gyro[b]:
                continue
            state = self._device(device)
            before = state.restarts
            state.update(
                int(seqs[b]),
                t_ns[lo:hi],
                (gyr[lo:hi], acc[lo:hi], field[lo:hi]),
                usable[lo:hi],
                saturated[lo:hi],
                raw[lo:hi],
                disturbed[lo:hi],
            )
            restarts += state.restarts - before
        dropped = {
            cause: int(n)
            for cause, n in (("gyro-non-finite", (gyro_rows & ~finite).sum()), ("gyro-saturated", saturated.sum()))
            if n
        }
        return FusedColumns.from_vqf(raw, disturbed, dropped, restarts)


def merge(headings: Headings, fused: FusedColumns) -> tuple[Headings, np.ndarray | None]:
    """The compass's headings (``magnet.compass.Headings``, S samples) with the fused attitude where there is one
    (flag FUSED; FIELD_DISTURBED also where vqf detects a disturbance; the other flags kept), and the fused attitude
    (S, 4) body -> magnetic NED, NaN rows where not fused, or None when no sample was fused (accelerometer tilt
    gives no quaternion, which keeps the messages of devices without a gyroscope as they were)."""
    f = fused.fused
    if not f.any():
        return headings, None
    flags = np.where(
        f,
        np.asarray(headings.flags)
        | int(hd.HeadingFlag.FUSED)
        | np.where(fused.mag_disturbed, int(hd.HeadingFlag.FIELD_DISTURBED), 0),
        headings.flags,
    )
    return dataclasses.replace(
        headings,
        heading_deg=np.where(f, fused.heading_deg, headings.heading_deg),
        pitch_deg=np.where(f, fused.pitch_deg, headings.pitch_deg),
        roll_deg=np.where(f, fused.roll_deg, headings.roll_deg),
        flags=flags,
    ), fused.quat_wxyz
