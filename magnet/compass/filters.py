"""One gyroscope-aided filter per device for the compass (DESIGN.md 4b): state kept across batches.

The compass computes accelerometer-tilt headings for every sample of a step (``magnet.compass.tilt``) and hands the
batches that carry a gyroscope to ``DeviceFilters.update``, which runs each device's ``magnet.attitude.fusion.Fusion``
on them; ``tilt.merge`` puts the fused attitude in place of the tilt one. A device's batches that continue one another
go through vqf in one call (about 4 us per call plus 0.5 us per sample). Per device:

- the filter runs at the device's sample period (the mean step of its first batch's ``t_ns`` in whole ns, so that a
  file as one batch and the same samples as many give the same filter); a period that changes by more than
  ``PERIOD_TOLERANCE`` gets a new filter;
- a batch whose ``seq`` does not follow the last one (the device restarted, or replays) or that comes more than
  ``MAX_GAP_S`` after the last sample restarts the filter: the rotation over a gap is unknown, and a restarted filter
  finds its tilt at once and its heading within seconds, where integrating across the gap would carry an error;
- non-finite gyroscope samples are skipped and counted (a short gap); saturated ones (a component at or beyond
  ``GYRO_LIMIT_RADS``) are skipped and restart the filter after them. Samples without a finite accelerometer or
  field are not fused either; samples not fused keep the tilt heading (flag FUSED clear), never NaN;
- vqf's magnetic disturbance detection sets FIELD_DISTURBED (the field is then left out of the heading); the compass
  judges the dip of fused samples against the fused gravity (``FusedColumns.gravity``);
- a new record restarts the filter's magnetic side (its first heading not from a field away from the record's
  strength: ``magnet.compass.first_heading``), or an aided filter's whole state (``magnet.compass.replay``);
- samples missing within a batch: the one after them turns over their time too, and after a stall the heading
  gate forgets its level (``magnet.compass.missed``).
State is bounded: at most ``MAX_DEVICES`` filters, the least recently used forgotten first.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

from magnet import _kernels
from magnet.attitude import fusion
from magnet.attitude.causal_drift import note_batch, take_drift
from magnet.attitude.offset_learn import take_off
from magnet.bounded import Recent
from magnet.compass import missed, replay
from magnet.compass.drain import Drain, make_drain
from magnet.compass.first_heading import FirstHeading

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
    fused; mag_disturbed (S,) bool. dropped: gyroscope samples dropped by cause; restarts: filters restarted.
    rotation: (S, 3, 3) the attitude's matrices body -> magnetic NED (the identity where not fused), or None (not
    computed: ``magnet.attitude.uncertainty`` makes them)."""

    fused: np.ndarray
    quat_wxyz: np.ndarray
    heading_deg: np.ndarray
    pitch_deg: np.ndarray
    roll_deg: np.ndarray
    down: np.ndarray
    mag_disturbed: np.ndarray
    dropped: Mapping[str, int]
    restarts: int
    rotation: np.ndarray | None = None

    @classmethod
    def empty(cls, count: int) -> FusedColumns:
        nan = np.full(count, np.nan)
        return cls(
            np.zeros(count, bool), np.full((count, 4), np.nan), nan, nan.copy(), nan.copy(),
            np.full((count, 3), np.nan), np.zeros(count, bool), {}, 0,
        )  # fmt: skip

    def gravity(self, acc_ms2: np.ndarray) -> np.ndarray:
        """Specific force (S, 3) as a still device would read it: -down (unit) where fused, else ``acc_ms2``."""
        if not self.fused.any():
            return acc_ms2
        gravity = np.negative(self.down)  # (np.where over rows of 3 broadcasts: 3-4 times the cost, the same values)
        if not self.fused.all():
            rest = ~self.fused
            gravity[rest] = acc_ms2[rest]
        return gravity

    @classmethod
    def from_vqf(
        cls, raw: np.ndarray, disturbed: np.ndarray, dropped: Mapping[str, int], restarts: int, rotations: bool = True
    ) -> FusedColumns:
        """From vqf's quaternions (S, 4) (NaN rows where not fused), converted to the project's frames at once, in
        one compiled pass (``magnet._kernels.vqf_attitudes``: ``frames.ned_enu_attitude``, ``quaternion_to_matrix``
        and ``matrix_to_euler``, sample by sample); the matrices kept with ``rotations`` (for the uncertainty)."""
        count = len(raw)
        fused, rotation = np.empty(count, dtype=bool), (np.empty((count, 3, 3)) if rotations else None)
        quat, down, angles = np.empty((count, 4)), np.empty((count, 3)), np.empty((3, count))
        _kernels.vqf_attitudes(
            np.asarray(raw, dtype=float), fused, quat, None if rotation is None else rotation.reshape(count, 9), down,
            *angles,
        )  # fmt: skip
        heading, pitch, roll = angles
        return cls(fused, quat, heading, pitch, roll, down, disturbed & fused, dict(dropped), restarts, rotation)


class DeviceFilter:
    """The filter of one device and what it needs to judge continuity (last seq, last time, period)."""

    def __init__(self, params: Mapping[str, Any] | None = None, max_gap_s: float = MAX_GAP_S) -> None:
        self.params = dict(params or {})
        self.max_gap_s = max_gap_s
        self.filter: fusion.Fusion | None = None
        self.last_seq: int | None = None
        self.last_t_ns: int | None = None
        self.restarts = 0
        #: an aided filter's last seconds, fed again with a new record (``recalibrate``, ``magnet.compass.replay``)
        self.recent: replay.RecentSamples | None = None
        self.first = FirstHeading()  # its first heading not taken from a field away from the record's strength

    def _period_s(self, first_ns: int, last_ns: int, count: int, span: float) -> float | None:
        """Mean step of the batch's times over its ``span`` periods (from the last sample for one); None: unusable."""
        if count >= 2:
            period = (last_ns - first_ns) / span * 1e-9  # exact ns steps give one period, whatever the batch
        elif self.last_t_ns is not None:
            period = (first_ns - self.last_t_ns) * 1e-9
        else:
            return None
        return period if fusion.MIN_PERIOD_S <= period <= fusion.MAX_PERIOD_S else None

    def _continues(self, seq: int, first_ns: int, period_s: float) -> bool:
        if self.filter is None or self.last_seq is None or self.last_t_ns is None:
            return False
        step_s = (first_ns - self.last_t_ns) * 1e-9
        same_rate = abs(self.filter.period_s - period_s) <= PERIOD_TOLERANCE * period_s
        return seq > self.last_seq and 0 < step_s <= self.max_gap_s + period_s and same_rate

    def update(self, drain: Drain, batches: list[int], out: np.ndarray, disturbed: np.ndarray) -> None:
        """Fuse this device's ``batches`` (indices into the drain, in order). Consecutive batches that continue one
        another go through vqf in one call (vqf is sample by sample: one call on their samples joined equals one
        call per batch). Writes vqf's quaternions into ``out`` (S, 4) and its disturbance flags into ``disturbed``
        (S,), both in the drain's permuted order, for the samples it fused."""
        lo = hi = 0  # the pending run of samples, not yet fed to the filter
        for b in batches:
            start, count, seq = drain.starts[b], drain.counts[b], drain.seqs[b]
            first, last = drain.first_ns[b], drain.last_ns[b]
            period = self._period_s(first, last, count, drain.spans[b])
            if period is None or not drain.increasing[b]:
                self._run(drain, lo, hi, out, disturbed)
                self.filter, self.last_seq, self.last_t_ns, lo, hi = None, seq, last, start, start
                continue
            if not self._continues(seq, first, period):
                self._run(drain, lo, hi, out, disturbed)
                self._restart(period)
                lo = hi = start
            if drain.batch_saturated[b]:
                lo = hi = self._saturated(drain, lo, hi, start, count, period, out, disturbed)
            elif drain.batch_stalled[b]:
                lo, hi = self._stalled(drain, lo, hi, start, count, out, disturbed), start + count
            else:
                if start != hi:  # not contiguous with the pending run (cannot happen within a device; kept safe)
                    self._run(drain, lo, hi, out, disturbed)
                    lo = start
                hi = start + count
            self.last_seq, self.last_t_ns = seq, last
        self._run(drain, lo, hi, out, disturbed)

    def _saturated(
        self, drain: Drain, lo: int, hi: int, start: int, count: int, period: float, out: Any, disturbed: Any
    ) -> int:
        """A batch with saturated samples: the pending run, then the pieces between them, a restart after each."""
        self._run(drain, lo, hi, out, disturbed)
        piece = start
        for stop in [*(np.flatnonzero(drain.saturated[start : start + count]) + start).tolist(), start + count]:
            self._run(drain, piece, stop, out, disturbed)
            if stop < start + count:
                self._restart(period)
            piece = stop + 1
        return start + count

    def _stalled(self, drain: Drain, lo: int, hi: int, start: int, count: int, out: Any, disturbed: Any) -> int:
        """A batch with samples after a stall: the samples before each fused, then the filter started again or the
        heading gate's usual level forgotten (``missed.start_again``); returns where the pending run now starts."""
        if start != hi:
            self._run(drain, lo, hi, out, disturbed)
            lo = start
        for stop in (np.flatnonzero(drain.stalled[start : start + count]) + start).tolist():
            self._run(drain, lo, stop, out, disturbed)
            if self.filter is not None and missed.start_again(self.filter):
                self._restart(self.filter.period_s)
            else:
                missed.heading_unknown(self.filter)
            lo = stop
        return lo

    def recalibrate(self, correct: replay.Corrector | None) -> None:
        """A new record in force: the filter forgets its magnetic side (``Fusion.restart_magnetometer``), or an aided
        one's recent samples are fused again with the record's ``correct``ion (``magnet.compass.replay.fuse_again``)."""
        if self.filter is not None and not replay.fuse_again(self.filter, self.recent, correct):
            self.filter.restart_magnetometer()
            take_drift(self, correct)  # the bias about the vertical from the last seconds, with the record
            self.first.start(self.filter)

    def _restart(self, period_s: float) -> None:
        if self.recent is not None:
            self.recent.clear()
        if self.filter is not None and abs(self.filter.period_s - period_s) <= PERIOD_TOLERANCE * period_s:
            self.filter.restart()
        else:
            self.filter = fusion.Fusion(period_s, self.params)
        self.first.start(self.filter)
        self.restarts += 1

    def _run(self, drain: Drain, lo: int, hi: int, out: np.ndarray, disturbed: np.ndarray) -> None:
        """Feed samples lo .. hi of the drain (the usable ones) to the filter; while it takes its first heading, those
        away from their record's strength without their field, the take begun again after them (``first_heading``)."""
        f = self.filter
        expected = None if f is None or f.aided else drain.expected_ut
        while f is not None and lo < hi:
            left_out, again = (None, None) if expected is None else self.first.judge(drain.inputs[2], expected, lo, hi)
            stop = hi if again is None else lo + again
            self._fuse(f, drain, lo, stop, out, disturbed)
            disturbed[lo:stop] |= False if left_out is None else left_out[: stop - lo]
            if again is not None:
                f.restart_magnetometer()
                self.first.start(f, again=True)
            lo = stop

    def _fuse(self, f: fusion.Fusion, drain: Drain, lo: int, hi: int, out: np.ndarray, disturbed: Any) -> None:
        """``_run``'s samples through the filter ``f``: in place in one compiled call, or the usable rows."""
        if drain.unusable_before[hi] == drain.unusable_before[lo]:
            if drain.aiding is None:  # the usual case: written in place, in one compiled call
                take_off(self, drain.inputs[2], lo, hi)  # the record's offset error learnt (``offset_learn``)
                f.update_rows(drain.inputs, lo, hi, out, disturbed)
                note_batch(self, drain, hi - 1, bool(disturbed[lo:hi].any()))  # the bias about the vertical
                return
            rows: Any = slice(lo, hi)
            gyr, acc, field = (x[lo:hi] for x in drain.inputs)
        else:
            rows = np.flatnonzero(drain.usable[lo:hi]) + lo
            if rows.size == 0:
                return
            gyr, acc, field = (np.ascontiguousarray(x[rows]) for x in drain.inputs)
        if drain.aiding is None:
            take_off(self, field, 0, len(field))  # (a copy here: the usable rows)
            out[rows], disturbed[rows] = f.update_vqf_frame(gyr, acc, field)
        else:
            t_s, vel = drain.aiding[0][rows], drain.aiding[1][rows]
            out[rows], disturbed[rows] = f.update_vqf_frame(gyr, acc, field, t_s, vel)
            if drain.raw is not None and f.aided:
                self.recent = replay.kept(self.recent, f.period_s, t_s, vel, gyr, acc, drain.raw[rows])


class DeviceFilters:
    """One ``DeviceFilter`` per device, at most ``max_devices`` (least recently used forgotten first, counted in
    ``evicted``)."""

    def __init__(
        self, params: Mapping[str, Any] | None = None, max_gap_s: float = MAX_GAP_S, max_devices: int = MAX_DEVICES
    ) -> None:
        self.params, self.max_gap_s = dict(params or {}), max_gap_s
        self.devices: Recent[str, DeviceFilter] = Recent(max_devices)

    @property
    def evicted(self) -> int:
        """Filters forgotten for the ``max_devices`` bound."""
        return self.devices.evicted

    def forget(self, device: str, magnetic_only: bool = False, correct: replay.Corrector | None = None) -> None:
        """Start the device's filter again on its next batch; ``magnetic_only``: its magnetic side only, now (a new
        calibration, whose ``correct``ion an aided filter's recent samples are fed again with: ``recalibrate``)."""
        state = self.devices.get(device) if magnetic_only else self.devices.pop(device, None)
        if magnetic_only and state is not None:
            state.recalibrate(correct)

    def _device(self, name: str) -> DeviceFilter:
        state = self.devices.get(name)
        if state is None:
            state = self.devices[name] = DeviceFilter(self.params, self.max_gap_s)
        else:
            self.devices.touch(name)
        return state

    def _any_aided(self, groups: Mapping[str, list[int]]) -> bool:
        """Whether the filter of a device of ``groups`` runs velocity-aided."""
        return any((s := self.devices.get(d)) is not None and s.filter is not None and s.filter.aided for d in groups)

    def update(
        self,
        devices: Sequence[str],
        seqs: Sequence[int],
        bounds: Sequence[int],
        t_ns: np.ndarray,
        gyr_rads: np.ndarray,
        acc_ms2: np.ndarray,
        field_ut: np.ndarray,
        vel_ned_ms: np.ndarray | None = None,
        rotations: bool = True,
        raw_ut: np.ndarray | None = None,
        expected_ut: np.ndarray | None = None,
    ) -> FusedColumns:
        """Fuse every batch b (samples bounds[b] .. bounds[b+1]) that carries a gyroscope (not all-NaN rows), in order;
        S = bounds[-1] samples, arrays (S, 3); ``vel_ned_ms`` (S, 3) m/s magnetic NED (NaN rows where unknown) aids
        the filters of the devices that send one (``magnet.attitude.aided_fusion``). Checks and frame conversions are
        done once for all samples; each device's batches are grouped, and its filter runs once per run of batches that
        continue one another. ``rotations``: the attitudes' matrices kept (``FusedColumns.rotation``); ``raw_ut``
        (S, 3) the raw field, kept by aided filters to fuse again with a new record (``magnet.compass.replay``);
        ``expected_ut`` (S,) the |B| each sample's record corrects to (``first_heading``; NaN where unknown)."""
        count = int(bounds[-1])
        edges = np.asarray(bounds, dtype=np.int64)
        sizes = np.diff(edges)
        present, finite, saturated, usable = np.empty((4, count), dtype=bool)  # the checks in one compiled pass
        _kernels.gyro_rows(gyr_rads, acc_ms2, field_ut, GYRO_LIMIT_RADS, present, finite, saturated, usable)
        if not present.any():
            return FusedColumns.empty(count)
        with_gyro = np.zeros(len(sizes), dtype=bool)
        nonempty = sizes > 0
        with_gyro[nonempty] = np.logical_or.reduceat(present, edges[:-1][nonempty])
        groups: dict[str, list[int]] = {}
        for b in np.flatnonzero(with_gyro).tolist():
            groups.setdefault(devices[b], []).append(b)
        order = None if len(groups) == int(with_gyro.sum()) else _device_order(groups, sizes)
        gyr_rads, spans, stalled = missed.spanned(gyr_rads, t_ns, edges)
        drain = make_drain(order, edges, seqs, t_ns, (gyr_rads, acc_ms2, field_ut), usable, saturated, spans, stalled)
        drain = drain if raw_ut is None else drain._replace(raw_source=(raw_ut, order))
        if expected_ut is not None:
            drain = drain._replace(expected_ut=expected_ut if order is None else expected_ut[order])
        if vel_ned_ms is not None and (np.isfinite(vel_ned_ms).any() or self._any_aided(groups)):
            # an aided filter needs its samples' times with no velocity known too (docs/aiding.md, point 6)
            raw = None if raw_ut is None else fusion.to_vqf_frame(raw_ut if order is None else raw_ut[order])
            drain = drain._replace(aiding=replay.aiding_columns(order, t_ns, vel_ned_ms), raw=raw)
        raw = np.full((count, 4), np.nan)
        disturbed = np.zeros(count, dtype=bool)
        restarts = 0
        for device, batches in groups.items():
            state = self._device(device)
            before = state.restarts
            state.update(drain, batches, raw, disturbed)
            restarts += state.restarts - before
        if order is not None:
            raw[order], disturbed[order] = raw.copy(), disturbed.copy()
        gyro_rows = np.repeat(with_gyro, sizes)  # every sample of a batch that carries a gyroscope
        dropped = {
            cause: int(n)
            for cause, n in (("gyro-non-finite", (gyro_rows & ~finite).sum()), ("gyro-saturated", saturated.sum()))
            if n
        }
        return FusedColumns.from_vqf(raw, disturbed, dropped, restarts, rotations)


def _device_order(groups: Mapping[str, list[int]], sizes: np.ndarray) -> np.ndarray | None:
    """The sample permutation (S,) that puts each device's samples together (devices in ``groups`` order, batches
    without a gyroscope last), keeping their order; None where they already are (one device's file: no copies)."""
    rank = np.full(len(sizes), len(groups), dtype=np.int64)
    for g, batches in enumerate(groups.values()):
        rank[batches] = g
    if bool((np.diff(rank[sizes > 0]) >= 0).all()):
        return None
    return np.argsort(np.repeat(rank, sizes), kind="stable")
