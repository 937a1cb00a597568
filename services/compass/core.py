"""The compass's computation, no zenoh inside: raw batches decoded, calibrated, tilt-compensated (or fused with the
gyroscope), checked for disturbance, smoothed and encoded as heading messages, a whole drain at once."""

from __future__ import annotations

import dataclasses
import logging
from typing import Any

import numpy as np

from magnet import heading as hd
from magnet import signing, wire
from magnet.compass import Earth, Headings, compute_headings, smooth_tail
from magnet.fleet import EarthColumns, Places, disturbance_flags
from magnet.fleet_fusion import FleetFusion, FusedColumns, merge
from magnet.frames import rotate_heading, to_magnetic_ned
from magnet.shard import EVERY_DEVICE, Shard
from services.compass.calibrations import CalibrationsInForce
from services.compass.settings import DEFAULT_MAX_DEVICES
from services.compass.watch import FleetWatch

log = logging.getLogger("magnet.compass")

_ZERO3, _EYE3 = np.zeros(3), np.eye(3)


@dataclasses.dataclass(frozen=True)
class CompassStatus:
    """The answer of ``<prefix>/@status/<name>``."""

    name: str
    received_batches: int
    received_samples: int
    published_batches: int
    calibrations: int
    calibration_updates: int
    dropped: dict[str, int]
    evicted_devices: int = 0
    shard: str = "0/1"

    def to_dict(self) -> dict[str, Any]:
        fields = dataclasses.asdict(self)
        return {"v": wire.RECORD_VERSION, "service": "compass", **fields, "dropped_total": sum(self.dropped.values())}


@dataclasses.dataclass(frozen=True, eq=False)
class HeadingColumns:
    """``Headings`` of the samples of a ``wire.RawColumns`` plus true_heading_deg (S,), one calibration id (or
    "") and one declination (deg, of the device's place) per batch."""

    headings: Headings
    true_heading_deg: np.ndarray
    calibration_ids: list[str]
    declinations: list[float]
    quat_wxyz: np.ndarray | None = None  # (S, 4) body -> NED (true north) where fused, NaN rows elsewhere; or None


def _calibration_rows(
    cals: list[wire.DeviceCalibration | None], counts: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per sample: the offset (S, 3), matrix (S, 3, 3) and whether calibrated (S,) of its batch's calibration
    (identity where none; broadcast views, no copies, when no batch has one)."""
    total = int(counts.sum())
    if all(c is None for c in cals):
        return np.broadcast_to(_ZERO3, (total, 3)), np.broadcast_to(_EYE3, (total, 3, 3)), np.zeros(total, bool)
    offsets = np.array([c.calibration.offset if c else _ZERO3 for c in cals]).reshape(-1, 3)
    matrices = np.array([c.calibration.matrix if c else _EYE3 for c in cals]).reshape(-1, 3, 3)
    calibrated = np.array([c is not None for c in cals], dtype=bool)
    return np.repeat(offsets, counts, axis=0), np.repeat(matrices, counts, axis=0), np.repeat(calibrated, counts)


def _motor_rows(cals: list[wire.DeviceCalibration | None], columns: wire.RawColumns) -> np.ndarray | None:
    """(S, 3) uT the motors add at each sample (``magnet.motor``: the calibration's motor model times the batch's
    current or throttle; zero where either is unknown), or None when no batch's calibration has a motor model."""
    if all(c is None or c.calibration.motor is None for c in cals):
        return None
    out = np.zeros((int(columns.counts.sum()), 3))
    bounds = columns.bounds
    for i, cal in enumerate(cals):
        if cal is not None and cal.calibration.motor is not None:
            lo, hi = bounds[i], bounds[i + 1]
            out[lo:hi] = cal.calibration.motor.offset_ut(columns.current[lo:hi], columns.thr[lo:hi])
    return out


class Compass(CalibrationsInForce):
    """State of the compass loop: calibrations in force, smoothing tails, filters, counters. No zenoh inside."""

    def __init__(
        self,
        earth: Earth,
        window: int,
        trusted: signing.TrustedKeys | None = None,
        watch: FleetWatch | None = None,
        shard: Shard = EVERY_DEVICE,
        max_devices: int = DEFAULT_MAX_DEVICES,
    ) -> None:
        if window < 1:
            raise ValueError(f"--window must be >= 1, got {window}")
        super().__init__(
            trusted,
            watch
            if watch is not None
            else FleetWatch(Places(default_earth=earth, max_reported=max_devices), max_devices=max_devices),
            shard,
            max_devices,
        )
        self.earth = earth
        self.window = window
        # one gyroscope-aided filter per device that sends a gyroscope, at most max_devices
        self.fusion = FleetFusion(max_devices=max_devices)
        self.received_batches = self.received_samples = self.published_batches = 0
        self._key_devices: dict[str, str] = {}
        self.last: HeadingColumns | None = None  # the last drain's headings (for the ROS 2 side)

    def decode(self, items: list[tuple[str, bytes]], prefix: str) -> list[wire.RawBatch]:
        """Raw batches from (key, payload) pairs; malformed ones dropped and counted."""
        return self.decode_columns(items, prefix).batches()

    def decode_columns(self, items: list[tuple[str, bytes]], prefix: str) -> wire.RawColumns:
        """All good raw batches of ``items`` as columns (one numpy pass); malformed ones dropped and counted."""
        columns, errors = wire.decode_raw_many([payload for _, payload in items])
        refused = set()
        for index, exc in errors:
            refused.add(index)
            self.drops.drop(exc, "raw", log)
        keys = [key for index, (key, _) in enumerate(items) if index not in refused]
        mismatch = np.array(
            [self._key_device(key, prefix) != device for key, device in zip(keys, columns.devices)], dtype=bool
        )
        if mismatch.any():
            for key, device in zip(np.array(keys)[mismatch], np.array(columns.devices)[mismatch]):
                self.drops.drop(wire.key_mismatch(key, device), "raw", log)
            columns = columns.select(~mismatch)
        return columns

    def _key_device(self, key_expr: str, prefix: str) -> str | None:
        device = self._key_devices.get(key_expr)
        if device is None:
            try:
                device = wire.device_from_key(prefix, key_expr, wire.Kind.RAW)
            except wire.WireError:
                return None
            if len(self._key_devices) < 100_000:
                self._key_devices[key_expr] = device
        return device

    def compute(self, columns: wire.RawColumns) -> HeadingColumns:
        """Headings for every sample of ``columns`` (see ``magnet.compass.compute_headings``), smoothed per device,
        with true headings and the calibration id of each batch; counts what it received."""
        cals = [self.calibrations.get(device) for device in columns.devices]
        for device, cal in zip(columns.devices, cals):
            if cal is not None:
                self.calibrations.touch(device)
        counts = columns.counts
        offsets, matrices, calibrated = _calibration_rows(cals, counts)
        earths = self.watch.earths(columns.devices, columns.locations)
        where = EarthColumns.of(earths, counts)
        motor = _motor_rows(cals, columns)
        out = compute_headings(columns.mag_ut, columns.acc_ms2, offsets, matrices, calibrated, Earth(), motor)
        fused = self._fuse(columns, out, where.declination_deg)
        gravity = fused.gravity(columns.acc_ms2)  # fused where fused: the accelerometer also reads linear acceleration
        with np.errstate(invalid="ignore", divide="ignore"):
            dip = hd.dip_angle_deg(out.field_ut, gravity)
        out = dataclasses.replace(out, flags=out.flags | disturbance_flags(out.field_ut, gravity, dip, where))
        out, quat = merge(out, fused)
        self.watch.observe(columns.devices, columns.bounds, columns.t_ns, hd.row_norm(out.field_ut), dip)
        self._log_evictions()
        self.received_batches += len(columns.devices)
        self.received_samples += int(counts.sum())
        if self.window > 1:
            bounds = columns.bounds
            out = dataclasses.replace(
                out,
                heading_deg=np.concatenate(
                    [
                        self._smooth(device, out.heading_deg[bounds[i] : bounds[i + 1]])
                        for i, device in enumerate(columns.devices)
                    ]
                    or [np.empty(0)]
                ),
            )
        return HeadingColumns(
            out,
            hd.true_heading_deg(out.heading_deg, where.declination_deg),
            [c.id if c else "" for c in cals],
            [e.declination_deg for e in earths],
            None if quat is None else rotate_heading(quat, where.declination_deg),
        )

    def calibration_changed(self, device: str) -> None:
        """Start the device's filter again: its magnetometer state was built on the old correction, and the field
        jumping to the new one would look to vqf like a magnetic disturbance it takes tens of seconds to trust."""
        self.fusion.devices.pop(device, None)

    def evicted_count(self) -> int:
        """Per-device entries forgotten for --max-devices: calibrations, tails, places, drift trackers, filters."""
        return super().evicted_count() + self.fusion.evicted

    def _fuse(self, columns: wire.RawColumns, out: Headings, declination_deg: np.ndarray) -> FusedColumns:
        """The per-device filters run on the batches that carry a gyroscope (``magnet.fleet_fusion``), aided by the
        velocity where a batch carries one (turned to magnetic north by the declination of the device's place); bad
        gyroscope samples are counted as dropped (``raw:gyro-non-finite``, ``raw:gyro-saturated``)."""
        vel = columns.vel
        aiding = to_magnetic_ned(vel, np.nan_to_num(declination_deg)) if np.isfinite(vel).any() else None
        fused = self.fusion.update(
            columns.devices,
            columns.seqs,
            columns.bounds,
            columns.t_ns,
            columns.gyr_rads,
            columns.acc_ms2,
            out.field_ut,
            aiding,
        )
        for cause, count in fused.dropped.items():
            if self.drops.count(f"raw:{cause}"):
                log.warning("dropping gyroscope samples (%s); further ones only counted", cause)
            self.drops.counts[f"raw:{cause}"] += count - 1
        return fused

    def encode(self, columns: wire.RawColumns) -> list[bytes]:
        """One heading payload per raw batch of ``columns``, in order."""
        out = self.last = self.compute(columns)
        h = out.headings
        return wire.encode_headings(
            columns,
            h.heading_deg,
            out.true_heading_deg,
            h.pitch_deg,
            h.roll_deg,
            h.field_ut,
            h.flags,
            out.declinations,
            out.calibration_ids,
            out.quat_wxyz,
        )

    def process(self, batches: list[wire.RawBatch]) -> list[wire.HeadingBatch]:
        """Heading batches, one per raw batch, computed in one vectorized pass."""
        if not batches:
            return []
        columns = wire.RawColumns.from_batches(batches)
        out = self.compute(columns)
        h = out.headings
        bounds = columns.bounds
        quat = out.quat_wxyz
        return [
            wire.HeadingBatch(
                batch.device,
                batch.seq,
                batch.t_ns,
                h.heading_deg[lo:hi],
                out.true_heading_deg[lo:hi],
                h.pitch_deg[lo:hi],
                h.roll_deg[lo:hi],
                h.field_ut[lo:hi],
                declination,
                cal_id,
                h.flags[lo:hi],
                quat[lo:hi] if quat is not None and np.isfinite(quat[lo:hi]).all() else None,
            )
            for batch, cal_id, declination, lo, hi in zip(
                batches, out.calibration_ids, out.declinations, bounds[:-1], bounds[1:]
            )
        ]

    def _smooth(self, device: str, heading: np.ndarray) -> np.ndarray:
        smoothed, self.tails[device] = smooth_tail(self.tails.get(device, np.empty(0)), heading, self.window)
        self._log_evictions()
        return smoothed

    def status(self, name: str) -> CompassStatus:
        return CompassStatus(
            name,
            self.received_batches,
            self.received_samples,
            self.published_batches,
            len(self.calibrations),
            self.calibration_updates,
            dict(self.drops.counts),
            self.evicted_count(),
            str(self.shard),
        )
