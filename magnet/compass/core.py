"""The compass in one object with one step: ``CompassCore.step(raw, now_ns) -> HeadingColumns``.

A step takes the raw batches of many devices (``wire.RawColumns``, float64) and gives every sample's heading:
each batch's calibration in force corrects the field, offset, matrix, motors and lag in one place
(``calibrations.Correction``); the accelerometer gives a tilt-compensated heading (``tilt``); the batches that carry
a gyroscope go through their device's filter (``filters``); the field and dip are checked against what the World
Magnetic Model expects at the device's place (``places``, ``earth``; the day from ``now_ns`` unless the places have
a fixed date); the heading is smoothed per device (``--window``) and turned to true north by the declination; the
drift monitor sees the field (``watch``); the compasses of a vehicle (``<vehicle>-mag<N>``) are kept for their
comparison (``magnet.vehicle``, ``vehicle_report``).
Its parts are small objects the core holds, none inheriting another's state. ``decode`` and ``encode`` are the
wire's edges (bytes in and out, counted drops); the live service, ``magnet heading`` and the tests all call
``step``. Pure: no zenoh, no clock (``now_ns`` is given).
"""

from __future__ import annotations

import dataclasses
import logging
from collections.abc import Callable
from typing import Any

import numpy as np

from magnet import signing, wire
from magnet import vehicle as vehicles  # its comparison loaded when first used (vehicle_report)
from magnet.attitude import heading as hd
from magnet.attitude.uncertainty import FilterFigures, HeadingUncertainty, Sigmas
from magnet.bounded import Recent
from magnet.compass.calibrations import CalibrationsInForce, Correction, recalibrate_filter
from magnet.compass.filters import DeviceFilters, FusedColumns
from magnet.compass.first_heading import expected_columns
from magnet.compass.keys import DeviceKeys
from magnet.compass.presence import GONE, CalibratorPresence
from magnet.compass.silence import Silence
from magnet.compass.tilt import Headings, Smoothing, batches_with, compute_headings, field_flags, merge
from magnet.compass.watch import DeviceWatch
from magnet.drift.settings import DEFAULT_DRIFT, DriftSettings
from magnet.earth.expected import utc_date
from magnet.fleet.places import EarthColumns, Places
from magnet.frames import rotate_heading, to_magnetic_ned
from magnet.shard import EVERY_DEVICE, Shard
from magnet.vehicle.window import VehicleWindows

log = logging.getLogger("magnet.compass")

DEFAULT_MAX_DEVICES = 10_000
#: key expressions remembered per device bound (a raw key per device, and room for another kind)
KEYS_PER_DEVICE = 2


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
    calibrators: int = 0  # calibrators alive (their liveliness tokens)
    calibrators_state: str = "unseen"  # present | gone: the records in force held are kept and applied | unseen
    calibrators_gone_since_ns: int | None = None  # when the last calibrator went away (ns since the epoch)
    #: records applied although numbered below the one held: made later, from calibrators that lost their history
    calibrations_renumbered: int = 0
    #: batches left uncorrected because their sensor's hardware id is not the one their device's record names, and
    #: the devices held back now: {device: {"record": id, "sensor": id}} (docs/mavlink.md, hardware ids)
    hardware_mismatches: int = 0
    hardware_mismatched: dict[str, dict[str, int]] = dataclasses.field(default_factory=dict)
    sinks: dict[str, int] = dataclasses.field(default_factory=dict)  # the sinks' own counts (ROS 2 topics, ...)

    def to_dict(self) -> dict[str, Any]:
        fields = dataclasses.asdict(self)
        return {"v": wire.RECORD_VERSION, "service": "compass", **fields, "dropped_total": sum(self.dropped.values())}


@dataclasses.dataclass(frozen=True, eq=False)
class HeadingColumns:
    """The headings of the S samples of a ``wire.RawColumns`` (``Headings``: magnetic heading, pitch, roll, field,
    flags), plus true_heading_deg (S,), dip_deg (S,) (NaN without a tilt), one calibration id (or "") and one
    declination (deg, of the device's place) per batch, and the attitude (S, 4) body -> NED (true north) where fused
    (NaN rows elsewhere), or None when no sample was fused."""

    headings: Headings
    true_heading_deg: np.ndarray
    dip_deg: np.ndarray
    calibration_ids: list[str]
    declinations: list[float]
    quat_wxyz: np.ndarray | None = None
    #: (S,) one sigma of each sample's heading and of its tilt about each horizontal axis, deg
    #: (``magnet.attitude.uncertainty``); None: not computed
    heading_sigma_deg: np.ndarray | None = None
    tilt_sigma_deg: np.ndarray | None = None


def window_problem(window: Any) -> str | None:
    """What is wrong with a smoothing window (headings), or None: the one check of ``--window``."""
    if isinstance(window, bool) or not isinstance(window, int) or window < 1:
        return "must be a whole number >= 1"
    return None


@dataclasses.dataclass(frozen=True)
class CoreSettings:
    """What the core runs with: the smoothing window (headings, >= 1), the per-device state bound, the shard it
    serves, the drift thresholds (None: no drift alerts), whether the sigmas are worked out (off: None)."""

    window: int = 1
    max_devices: int = DEFAULT_MAX_DEVICES
    shard: Shard = EVERY_DEVICE
    drift: DriftSettings | None = DEFAULT_DRIFT
    sigmas: bool = True

    def __post_init__(self) -> None:
        problem = window_problem(self.window)
        if problem is not None:
            raise ValueError(f"--window {problem}, got {self.window!r}")


@dataclasses.dataclass
class Counters:
    """What the compass received and published (batches, samples)."""

    received_batches: int = 0
    received_samples: int = 0
    published_batches: int = 0


def _correction(cals: list[wire.DeviceCalibration | None]) -> Callable[[int], tuple[np.ndarray, np.ndarray] | None]:
    """Batch index -> its calibration's (offset, matrix), or None (asked only for the batches of vehicles)."""

    def of(b: int) -> tuple[np.ndarray, np.ndarray] | None:
        cal = cals[b]
        return None if cal is None else (np.asarray(cal.calibration.offset), np.asarray(cal.calibration.matrix))

    return of


class CompassCore:
    """The compass's state and its step (see the module). ``places``: where each device is (None: nowhere known);
    ``trusted``: the keys calibrations must be signed by (None: any)."""

    def __init__(
        self,
        settings: CoreSettings = CoreSettings(),
        places: Places | None = None,
        trusted: signing.TrustedKeys | None = None,
    ) -> None:
        self.settings = settings
        limit = settings.max_devices
        self.calibrations = CalibrationsInForce(trusted, limit)
        self.watch = DeviceWatch(places or Places(max_reported=limit), settings.drift, limit)
        self.filters = DeviceFilters(max_devices=limit)
        self.silence = Silence(limit)  # a device silent for a minute: its filter forgotten (magnet.compass.silence)
        self.smoothing = Smoothing(settings.window, limit)
        self.uncertainty = HeadingUncertainty(limit)
        self.vehicles = VehicleWindows(limit)
        self.keys = DeviceKeys(settings.shard, max_keys=KEYS_PER_DEVICE * limit)
        self.drops = wire.DropCounter()
        self.counters = Counters()
        self.sink_counts: dict[str, int] = {}  # what the sinks count of their own (status ``sinks``)
        self.calibrators = CalibratorPresence()
        self._evictions_logged = False
        self._mismatch_logged: Recent[str, tuple[int, int]] = Recent(limit)

    # ------------------------------------------------------------------------------------------ the wire's edges
    def decode(self, items: list[tuple[str, bytes]], prefix: str) -> wire.RawColumns:
        """All good raw batches of (key, payload) ``items`` as columns (one numpy pass, float64); malformed ones and
        those whose key names another device dropped and counted."""
        columns, errors = wire.decode_raw_many([payload for _, payload in items])
        refused = set()
        for index, exc in errors:
            refused.add(index)
            self.drops.drop(exc, "raw", log)
        keys = [key for index, (key, _) in enumerate(items) if index not in refused]
        mismatch = np.array(
            [self.keys.device(key, prefix) != device for key, device in zip(keys, columns.devices)], dtype=bool
        )
        if mismatch.any():
            for key, device in zip(np.array(keys)[mismatch], np.array(columns.devices)[mismatch]):
                self.drops.drop(wire.key_mismatch(key, device), "raw", log)
            columns = columns.select(~mismatch)
        return columns

    @staticmethod
    def encode(raw: wire.RawColumns, out: HeadingColumns) -> list[bytes]:
        """One heading payload per raw batch of ``raw``, in order (float32 on the wire, from here only)."""
        h = out.headings
        return wire.encode_headings(
            raw,
            h.heading_deg,
            out.true_heading_deg,
            h.pitch_deg,
            h.roll_deg,
            h.field_ut,
            h.flags,
            out.declinations,
            out.calibration_ids,
            out.quat_wxyz,
            out.heading_sigma_deg,
        )

    def accept_calibration(self, payload: bytes, key_expr: str, prefix: str) -> bool:
        """Apply a calibration message when it is usable (``CalibrationsInForce.check``); else count why, keep the
        one in force and remember the device so that the calibrators are asked again. True when it is (or already
        was) in force; False, silently, for another shard's device."""
        if not self.keys.mine(key_expr, prefix, wire.Kind.CALIBRATION):
            return False
        try:
            record = wire.decode_calibration(payload)
            wire.check_key(prefix, key_expr, wire.Kind.CALIBRATION, record.device)
            renumbered = self.calibrations.check(record)
        except wire.WireError as exc:
            self.drops.drop(exc, "calibration", log)
            device = self.keys.device(key_expr, prefix, wire.Kind.CALIBRATION)
            if device is not None:
                self.calibrations.refuse(device)
            return False
        if renumbered is not None:
            log.warning("%s", renumbered)
        previous = self.calibrations.in_force.get(record.device)
        if self.calibrations.put(record):
            self._log_evictions()
            self.watch.calibration(record, record.created_ns)
            recalibrate_filter(self.filters, previous, record)
            log.info("calibration %s (%s) in force for %s", record.id, record.calibration.method, record.device)
        return True

    # ------------------------------------------------------------------------------------------------- the step
    def step(self, raw: wire.RawColumns, now_ns: int) -> HeadingColumns:
        """Headings for every sample of ``raw`` (see the module); ``now_ns`` the wall clock (ns since the epoch),
        whose UTC day dates the model where no ``--date`` is fixed. Counts what it received."""
        cals = self.calibrations.of_batches(raw.devices, raw.hardware_ids)
        self._log_mismatches()
        correction = Correction.of_batches(cals, raw)
        field, filter_field = correction.apply(raw.mag_ut, raw.gyr_rads)
        earths = self.watch.earths(raw.devices, raw.locations, utc_date(now_ns))
        where = EarthColumns.of(earths, raw.counts)
        filter_field, flags = field_flags(filter_field, field, correction.calibrated, where.total_ut)
        for device in self.silence.heard(raw.devices, now_ns):
            self.filters.forget(device)
        fused = self._fuse(raw, filter_field, where, cals)
        out = compute_headings(field, raw.acc_ms2, flags, fused.fused)  # the accelerometer's tilt where not fused
        gravity = fused.gravity(raw.acc_ms2)  # fused where fused: the accelerometer also reads linear acceleration
        with np.errstate(invalid="ignore", divide="ignore"):
            dip = hd.dip_angle_deg(out.field_ut, gravity)
        flags = hd.disturbance_flags(out.field_ut, gravity, where.total_ut, where.inclination_deg, dip_deg=dip)
        out, quat = merge(dataclasses.replace(out, flags=out.flags | flags), fused)
        sigma = self._sigma(raw, out, quat, fused, where.total_ut, cals) if self.settings.sigmas else None
        self.watch.observe(raw.devices, raw.bounds, raw.t_ns, hd.row_norm(out.field_ut), dip)
        self.vehicles.observe(
            raw.devices, raw.bounds, raw.t_ns, raw.mag_ut, raw.current, raw.thr, _correction(cals), raw.vehicles
        )
        self._log_evictions()
        self.counters.received_batches += len(raw.devices)
        self.counters.received_samples += int(raw.counts.sum())
        out = dataclasses.replace(out, heading_deg=self.smoothing.apply(raw.devices, raw.bounds, out.heading_deg))
        return HeadingColumns(
            out,
            hd.true_heading_deg(out.heading_deg, where.declination_deg),
            dip,
            [c.id if c else "" for c in cals],
            [e.declination_deg for e in earths],
            None if quat is None else rotate_heading(quat, where.declination_deg),
            *(sigma or (None, None)),
        )

    def _sigma(
        self,
        raw: wire.RawColumns,
        out: Headings,
        quat: np.ndarray | None,
        fused: FusedColumns,
        expected_ut: np.ndarray,
        cals: list[wire.DeviceCalibration | None],
    ) -> Sigmas:
        """Each sample's heading and tilt sigmas (S,) deg (``magnet.attitude.uncertainty``): from the calibration's
        residual, the field, the flags and, where fused, the device's filter's figures after this step."""
        bounds, states = raw.bounds, [self.filters.devices.get(device) for device in raw.devices]
        figures: list[FilterFigures | None] = [
            s.filter.figures() if s is not None and s.filter is not None and fused_b else None
            for s, fused_b in zip(states, batches_with(fused.fused, raw.counts))
        ]
        residuals = [None if c is None else c.calibration.quality.residual_rms_ut for c in cals]
        samples = (raw.t_ns, raw.acc_ms2, out.field_ut, out.flags, quat, expected_ut)
        return self.uncertainty.step(raw.devices, bounds, *samples, residuals, figures, fused.rotation)

    def _fuse(
        self, raw: wire.RawColumns, field: np.ndarray, where: EarthColumns, cals: list[wire.DeviceCalibration | None]
    ) -> FusedColumns:
        """The devices' filters (``magnet.compass.filters``) on the batches with a gyroscope, aided by a velocity
        where a batch has one (turned to magnetic north by the declination at ``where``); bad gyroscope samples
        counted as dropped (``raw:gyro-non-finite``, ``raw:gyro-saturated``). ``field`` (S, 3) uT as the filters get
        it (``Correction.apply``); each batch's record ``cals`` gives its first heading's |B| (``first_heading``)."""
        expected_ut = expected_columns(cals, raw.counts, where.total_ut)
        vel = raw.vel  # with no velocity known (NaN rows) as it is: a filter already aided still needs the times
        aiding = to_magnetic_ned(vel, np.nan_to_num(where.declination_deg)) if np.isfinite(vel).any() else vel
        columns = (raw.devices, raw.seqs, raw.bounds, raw.t_ns, raw.gyr_rads, raw.acc_ms2, field, aiding)
        fused = self.filters.update(
            *columns, rotations=self.settings.sigmas, raw_ut=raw.mag_ut, expected_ut=expected_ut
        )
        for cause, count in fused.dropped.items():
            if self.drops.count(f"raw:{cause}"):
                log.warning("dropping gyroscope samples (%s); further ones only counted", cause)
            self.drops.counts[f"raw:{cause}"] += count - 1
        return fused

    def vehicle_report(self, vehicle: str) -> vehicles.VehicleReport | None:
        """The compasses of ``vehicle`` judged against each other (``magnet.vehicle.judge``), with the field the WMM
        expects at the place of its first compass; None for a vehicle not seen."""
        series = self.vehicles.series(vehicle)
        if not series:
            return None
        earth = self.watch.places.earth(next(iter(series)), self.watch.date)
        return vehicles.judge(vehicle, series, earth.total_ut)

    # ------------------------------------------------------------------------------------------------ counters
    def evicted_count(self) -> int:
        """Per-device entries forgotten for --max-devices: calibrations, tails, places, drift trackers, filters."""
        return (
            self.calibrations.in_force.evicted
            + self.smoothing.tails.evicted
            + self.watch.evicted
            + self.filters.evicted
        )

    def _log_mismatches(self) -> None:
        """One warning per device and pair of ids whose record is held back from another sensor's batches."""
        for device, (record_id, sensor_id) in self.calibrations.mismatched.items():
            if self._mismatch_logged.get(device) != (record_id, sensor_id):
                self._mismatch_logged[device] = (record_id, sensor_id)
                log.warning(
                    "%s: its calibration was made for sensor %d but the samples come from sensor %d (a compass "
                    "missing at boot moves the others up): not applied; counted in status hardware_mismatches",
                    device,
                    record_id,
                    sensor_id,
                )

    def _log_evictions(self) -> None:
        if not self._evictions_logged and self.evicted_count():
            self._evictions_logged = True
            log.warning(
                "more than %d devices: the least recently seen are forgotten (counted in status "
                "evicted_devices; raise --max-devices if they are genuine)",
                self.settings.max_devices,
            )

    def on_calibrator(self, key: str, alive: bool, now_ns: int) -> None:
        """A calibrator's liveliness token appeared or went away: when the last one goes, the records in force held
        stay (nothing here drops them) and that is logged and shown in the status."""
        if not self.calibrators.on_token(key, alive, now_ns):
            return
        held = len(self.calibrations.in_force)
        if self.calibrators.state == GONE:
            log.warning("every calibrator is gone: the %d calibration(s) in force held are kept and applied", held)
        else:
            log.info("a calibrator is back (%s): %d calibration(s) in force held", key, held)

    def status(self, name: str) -> CompassStatus:
        c = self.counters
        return CompassStatus(
            name,
            c.received_batches,
            c.received_samples,
            c.published_batches,
            len(self.calibrations.in_force),
            self.calibrations.updates,
            dict(self.drops.counts),
            self.evicted_count(),
            str(self.settings.shard),
            len(self.calibrators.alive),
            self.calibrators.state,
            self.calibrators.gone_since_ns,
            self.calibrations.renumbered,
            self.calibrations.hardware_mismatches,
            self.calibrations.mismatch_report(),
            dict(self.sink_counts),
        )
