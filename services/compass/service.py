"""``magnet compass``: apply each device's calibration to its raw batches, tilt-compensate with the accelerometer, add
the WMM declination, and publish one heading message per raw batch on ``<prefix>/<device>/heading``.

On start it queries every stored calibration (``<prefix>/*/calibration``) and then follows new ones (subscriber);
a device with none is asked for again now and then, and meanwhile gets headings from its raw field (flag
CALIBRATED clear). Zenoh delivers into channels; this process's own loop drains them, decodes, computes a whole
drain of batches at once (``magnet.compass.compute_headings``, vectorized over every sample of every device) and
publishes, never inside a callback. Counters (received, published, dropped by cause) answer on
``<prefix>/@status/<name>``.
"""

from __future__ import annotations

import argparse
import dataclasses
import logging
import time
from pathlib import Path
from typing import Any

import numpy as np
import zenoh

from magnet import heading as hd
from magnet import signing, wire
from magnet.bounded import Recent
from magnet.compass import Earth, Headings, compute_headings, smooth_tail
from magnet.drift import DEFAULT_DRIFT, DriftSettings
from magnet.fleet import EarthColumns, Places, disturbance_flags
from magnet.fleet_fusion import FleetFusion, FusedColumns, merge
from magnet.fusion import rotate_heading
from magnet.place import Location
from magnet.shard import EVERY_DEVICE, Shard
from services.common.fleet_options import add_drift_arguments, add_fleet_argument, drift_from_args, read_fleet
from services.common.zenoh_session import (
    ZenohSettings,
    add_zenoh_arguments,
    drain,
    open_session,
    payload_bytes,
    stop_event,
)
from services.compass.watch import FleetWatch

log = logging.getLogger("magnet.compass")

MAX_DRAIN = 4000  # raw messages computed together at most
CHANNEL_CAPACITY = 65536  # raw messages queued between zenoh and this loop
REQUERY_S = 5.0  # how often to ask again for the calibration of a device that has none
REQUERY_REFUSED_S = 1.0  # how often at most to ask the calibrators again after refusing a calibration
DEFAULT_MAX_DEVICES = 10_000
MAX_REFUSED = 1024  # devices remembered for that between two asks (a flood beyond: one query for all)
IDLE_SLEEP_S = 0.0003
_ZERO3, _EYE3 = np.zeros(3), np.eye(3)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--location",
        help="LAT,LON[,ALT_M] for the WMM declination and expected field "
        "(without it: declination 0, no field/dip disturbance check)",
    )
    parser.add_argument("--date", help="date for the WMM (YYYY-MM-DD; default today)")
    parser.add_argument("--window", type=int, default=1, help="circular sliding mean over N headings (default 1)")
    parser.add_argument("--name", default="compass", help="service name for liveliness and status (default compass)")
    parser.add_argument(
        "--devices",
        default="*",
        help="key expression of the devices this instance serves (default *, all); e.g. 'line-1-*'",
    )
    parser.add_argument(
        "--max-devices",
        type=int,
        default=DEFAULT_MAX_DEVICES,
        help="devices whose state (calibration, smoothing, keys) is kept at most; beyond, the least "
        f"recently seen is forgotten (default {DEFAULT_MAX_DEVICES})",
    )
    parser.add_argument(
        "--trust",
        action="append",
        default=[],
        type=Path,
        metavar="FILE.pub",
        help="apply only calibrations signed by this public key (repeatable; `magnet keys` makes "
        "them). Without it, unsigned calibrations are applied too",
    )
    parser.add_argument(
        "--shard",
        default="0/1",
        metavar="K/N",
        help="serve only the devices of shard K of N (0 <= K < N; see magnet.shard: sha256 of the "
        "device id, first 8 bytes, mod N); default 0/1, every device",
    )
    add_fleet_argument(parser)
    add_drift_arguments(parser)
    add_zenoh_arguments(parser)


@dataclasses.dataclass(frozen=True)
class CompassSettings:
    """Everything ``magnet compass`` runs with: what it expects where it is, the smoothing window (headings), its
    name, the devices it serves (a key expression chunk) and the Zenoh options."""

    earth: Earth = Earth()
    window: int = 1
    name: str = "compass"
    devices: str = "*"
    zenoh: ZenohSettings = ZenohSettings()
    trust: tuple[Path, ...] = ()
    max_devices: int = DEFAULT_MAX_DEVICES
    places: tuple[Location | None, str | None, dict[str, Any]] = (None, None, {})  # default, date, fleet file
    drift: DriftSettings | None = DEFAULT_DRIFT
    shard: Shard = EVERY_DEVICE

    def __post_init__(self) -> None:
        if isinstance(self.window, bool) or not isinstance(self.window, int) or self.window < 1:
            raise ValueError(f"--window must be >= 1, got {self.window}")


def settings_from_args(args: argparse.Namespace) -> CompassSettings:
    default = Location.parse(args.location) if args.location else None
    return CompassSettings(
        Earth.from_args(args.location, args.date),
        args.window,
        args.name,
        args.devices,
        ZenohSettings.from_args(args),
        tuple(args.trust),
        max_devices=args.max_devices,
        places=(default, args.date, read_fleet(args.fleet)),
        drift=drift_from_args(args),
        shard=Shard.parse(args.shard),
    )


def load_trusted_keys(paths: tuple[Path, ...] | list[Path]) -> signing.TrustedKeys:
    """The public keys of ``--trust`` files; OSError/ValueError naming a file that cannot be used."""
    return signing.TrustedKeys([signing.load_public_key(path.read_bytes(), str(path)) for path in paths])


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
        return {"v": wire.WIRE_VERSION, "service": "compass", **fields, "dropped_total": sum(self.dropped.values())}


@dataclasses.dataclass(frozen=True, eq=False)
class HeadingColumns:
    """``Headings`` of the samples of a ``wire.RawColumns`` plus true_heading_deg (S,), one calibration id (or
    "") and one declination (deg, of the device's place) per batch."""

    headings: Headings
    true_heading_deg: np.ndarray
    calibration_ids: list[str]
    declinations: list[float]
    quat_wxyz: np.ndarray | None = None  # (S, 4) body -> NED (true north) where fused, NaN rows elsewhere; or None


class Compass:
    """State of the compass loop: calibrations in force, smoothing tails, counters. No zenoh inside."""

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
        self.earth = earth
        self.window = window
        self.trusted = trusted or signing.TrustedKeys()
        self.refused: set[str] = set()  # devices whose calibration was refused since the calibrators were last asked
        self.refused_overflow = False
        self.calibrations: Recent[str, wire.DeviceCalibration] = Recent(max_devices)
        self.tails: Recent[str, np.ndarray] = Recent(max_devices)
        self.max_devices = max_devices
        self._evictions_logged = False
        self.fusion = FleetFusion()  # one gyroscope-aided filter per device that sends a gyroscope
        self.drops = wire.DropCounter()
        self.received_batches = self.received_samples = self.published_batches = 0
        self.calibration_updates = 0
        self._key_devices: dict[str, str] = {}
        self.watch = watch if watch is not None else FleetWatch(Places(default_earth=earth))
        self.shard = shard
        self._mine: dict[str, bool] = {}

    def mine(self, key_expr: str, prefix: str, kind: wire.Kind = wire.Kind.RAW) -> bool:
        """Whether the device of ``key_expr`` belongs to this compass's shard (a malformed key: True, so that it is
        decoded, refused and counted)."""
        owned = self._mine.get(key_expr)
        if owned is None:
            try:
                owned = self.shard.owns(wire.device_from_key(prefix, key_expr, kind))
            except wire.WireError:
                return True
            if len(self._mine) < 200_000:
                self._mine[key_expr] = owned
        return owned

    def accept_calibration(self, payload: bytes, key_expr: str, prefix: str) -> bool:
        """Apply a calibration message when it is usable (``applicable``); else count why, keep the one in force and
        remember the device so that the calibrators are asked again. True when it is (or already was) in force;
        False, silently, for another shard's device."""
        if not self.shard.everything and not self.mine(key_expr, prefix, wire.Kind.CALIBRATION):
            return False
        try:
            record = wire.decode_calibration(payload)
            wire.check_key(prefix, key_expr, wire.Kind.CALIBRATION, record.device)
            self.applicable(record)
        except wire.WireError as exc:
            self.drops.drop(exc, "calibration", log)
            self._remember_refused(key_expr, prefix)
            return False
        current = self.calibrations.get(record.device)
        if current is None or current.id != record.id:
            self.calibrations[record.device] = record
            self.calibration_updates += 1
            self._log_evictions()
            self.watch.calibration(record, record.created_ns)
            log.info("calibration %s (%s) in force for %s", record.id, record.calibration.method, record.device)
        return True

    def applicable(self, record: wire.DeviceCalibration) -> None:
        """WireError unless ``record`` may be applied: accepted by the quality gate (its plausibility was checked
        when it was read), signed by a trusted key where keys are trusted, and not older than the one in force."""
        if not record.calibration.accepted:
            raise wire.WireError(
                "not-accepted",
                f"calibration {record.id} of {record.device} is marked accepted: false (the quality gate refused it)",
            )
        if self.trusted.enabled:
            try:
                self.trusted.verify(record.to_record())
            except signing.SignatureError as exc:
                raise wire.WireError(exc.cause, f"calibration {record.id} of {record.device}: {exc}") from None
        current = self.calibrations.get(record.device)
        if current is not None and current.id != record.id and record.created_ns < current.created_ns:
            raise wire.WireError(
                "stale", f"calibration {record.id} of {record.device} is older than the one in force ({current.id})"
            )

    def _remember_refused(self, key_expr: str, prefix: str) -> None:
        try:
            device = wire.device_from_key(prefix, key_expr, wire.Kind.CALIBRATION)
        except wire.WireError:
            return
        if len(self.refused) < MAX_REFUSED:
            self.refused.add(device)
        else:
            self.refused_overflow = True

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
        offsets = np.repeat(
            np.array([c.calibration.offset if c else _ZERO3 for c in cals]).reshape(-1, 3), counts, axis=0
        )
        matrices = np.repeat(
            np.array([c.calibration.matrix if c else _EYE3 for c in cals]).reshape(-1, 3, 3), counts, axis=0
        )
        calibrated = np.repeat(np.array([c is not None for c in cals], dtype=bool), counts)
        earths = self.watch.earths(columns.devices, columns.locations)
        where = EarthColumns.of(earths, counts)
        out = compute_headings(columns.mag_ut, columns.acc_ms2, offsets, matrices, calibrated, Earth())
        fused = self._fuse(columns, out)
        gravity = fused.gravity(columns.acc_ms2)  # fused where fused: the accelerometer also reads linear acceleration
        with np.errstate(invalid="ignore", divide="ignore"):
            dip = hd.dip_angle_deg(out.field_ut, gravity)
        out = dataclasses.replace(out, flags=out.flags | disturbance_flags(out.field_ut, gravity, dip, where))
        out, quat = merge(out, fused)
        self.watch.observe(columns.devices, columns.bounds, columns.t_ns, np.linalg.norm(out.field_ut, axis=1), dip)
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

    def _fuse(self, columns: wire.RawColumns, out: Headings) -> FusedColumns:
        """The per-device filters run on the batches that carry a gyroscope (``magnet.fleet_fusion``); bad gyroscope
        samples are counted as dropped (``raw:gyro-non-finite``, ``raw:gyro-saturated``)."""
        fused = self.fusion.update(
            columns.devices, columns.seqs, columns.bounds, columns.t_ns, columns.gyr_rads, columns.acc_ms2, out.field_ut
        )
        for cause, count in fused.dropped.items():
            if self.drops.count(f"raw:{cause}"):
                log.warning("dropping gyroscope samples (%s); further ones only counted", cause)
            self.drops.counts[f"raw:{cause}"] += count - 1
        return fused

    def encode(self, columns: wire.RawColumns) -> list[bytes]:
        """One heading payload per raw batch of ``columns``, in order."""
        out = self.compute(columns)
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

    def _log_evictions(self) -> None:
        if not self._evictions_logged and self.calibrations.evicted + self.tails.evicted:
            self._evictions_logged = True
            log.warning(
                "more than %d devices: the least recently seen are forgotten (counted in status "
                "evicted_devices; raise --max-devices if they are genuine)",
                self.max_devices,
            )

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
            self.calibrations.evicted + self.tails.evicted,
            str(self.shard),
        )


# ------------------------------------------------------------------------------------------------------- shell


def run_compass(args: argparse.Namespace) -> int:
    """``magnet compass``: the settings from the options, then ``run``."""
    return run(settings_from_args(args))


def run(settings: CompassSettings) -> int:
    default, date, fleet = settings.places
    watch = FleetWatch(Places(fleet, default, date, settings.earth), settings.drift)
    compass = Compass(
        settings.earth, settings.window, load_trusted_keys(settings.trust), watch, settings.shard, settings.max_devices
    )
    if compass.trusted.enabled:
        log.info("compass applies only calibrations signed by key(s) %s", ", ".join(compass.trusted.key_ids))
    stop = stop_event()
    prefix, devices, name = settings.zenoh.prefix, settings.devices, settings.name
    with open_session(settings.zenoh) as session:
        token = session.liveliness().declare_token(wire.liveliness_key(prefix, "compass", name))
        raw_sub = session.declare_subscriber(f"{prefix}/{devices}/raw", zenoh.handlers.FifoChannel(CHANNEL_CAPACITY))
        cal_sub = session.declare_subscriber(f"{prefix}/{devices}/calibration", zenoh.handlers.FifoChannel(1024))
        status_q = session.declare_queryable(wire.status_key(prefix, name), zenoh.handlers.FifoChannel(64))
        alert_q = session.declare_queryable(
            f"{prefix}/{devices}/{wire.Kind.ALERT.value}", zenoh.handlers.FifoChannel(64)
        )
        log.info(
            "compass %s: serving %s/%s (shard %s), declination %.2f deg",
            name,
            prefix,
            devices,
            settings.shard,
            compass.earth.declination_deg,
        )
        loop = _Loop(session, compass, settings)
        while not stop.is_set():
            loop.calibrations(cal_sub)
            for query in drain(status_q, 64):
                query.reply(wire.status_key(prefix, name), wire.pack(compass.status(name).to_dict()))
                query.drop()  # finalize now: the asker waits for it
            loop.alerts(alert_q)
            if not loop.headings(raw_sub):
                time.sleep(IDLE_SLEEP_S)
        token.undeclare()
    log.info("compass stopped: %s", compass.status(name).to_dict())
    return 0


class _Loop:
    """One compass loop's session work: calibration queries and their replies, headings published."""

    def __init__(self, session: Any, compass: Compass, settings: CompassSettings) -> None:
        self.session, self.compass = session, compass
        self.prefix, self.devices = settings.zenoh.prefix, settings.devices
        self.heading_keys: Recent[str, str] = Recent(settings.max_devices)
        self.asked = self.asked_refused = time.monotonic()
        self.pending: list[tuple[float, Any]] = [(self.asked + 3.0, self._ask(3.0))]

    def _ask(self, timeout: float, devices: str | None = None) -> Any:
        return self.session.get(f"{self.prefix}/{devices or self.devices}/calibration", timeout=timeout)

    def _ask_refused(self) -> None:
        """Ask the calibrators again for the calibrations of devices whose calibration was just refused (a forged or
        stale one may have hidden a genuine update), at most every REQUERY_REFUSED_S."""
        now = time.monotonic()
        if not (self.compass.refused or self.compass.refused_overflow) or now - self.asked_refused < REQUERY_REFUSED_S:
            return
        self.asked_refused = now
        refused = sorted(self.compass.refused)
        if self.compass.refused_overflow or len(refused) > 8:
            refused = [self.devices]
        self.compass.refused.clear()
        self.compass.refused_overflow = False
        self.pending += [(now + 2.0, self._ask(2.0, device)) for device in refused]

    def calibrations(self, cal_sub: Any) -> None:
        """Take the calibrations published and the replies to queries that arrived; keep queries that may answer."""
        still, now = [], time.monotonic()
        for deadline, handler in self.pending:
            for reply in drain(handler, 10_000):
                if reply.ok is not None:
                    self.compass.accept_calibration(payload_bytes(reply.ok), str(reply.ok.key_expr), self.prefix)
            if now < deadline:
                still.append((deadline, handler))
        self.pending = still
        for sample in drain(cal_sub, 1000):
            self.compass.accept_calibration(payload_bytes(sample), str(sample.key_expr), self.prefix)
        self._ask_refused()

    def headings(self, raw_sub: Any) -> bool:
        """Compute and publish the headings of the raw batches waiting; False when there were none."""
        samples = drain(raw_sub, MAX_DRAIN)
        if not samples:
            return False
        keys = [str(s.key_expr) for s in samples]
        if not self.compass.shard.everything:  # another shard's devices: dropped by key, before any decoding
            mine = [i for i, k in enumerate(keys) if self.compass.mine(k, self.prefix)]
            samples, keys = [samples[i] for i in mine], [keys[i] for i in mine]
        columns = self.compass.decode_columns([(k, s.payload.to_bytes()) for s, k in zip(samples, keys)], self.prefix)
        for device, payload in zip(columns.devices, self.compass.encode(columns)):
            key = self.heading_keys.get(device) or self.heading_keys.setdefault(
                device, wire.key(self.prefix, device, wire.Kind.HEADING)
            )
            self.session.put(key, payload)  # measured: a declared publisher per device costs ~5x the CPU
            self.compass.published_batches += 1
        self._ask_missing(columns.devices)
        return True

    def alerts(self, alert_q: Any) -> None:
        """Publish the alerts raised or cleared; answer queries for the open ones."""
        for alert in self.compass.watch.take():
            self.session.put(wire.key(self.prefix, alert.device, wire.Kind.ALERT), wire.pack(alert.to_message()))
        for query in drain(alert_q, 16):
            asked = zenoh.KeyExpr(str(query.key_expr))
            for alert in self.compass.watch.open_alerts():
                key = wire.key(self.prefix, alert.device, wire.Kind.ALERT)
                if asked.intersects(zenoh.KeyExpr(key)):
                    query.reply(key, wire.pack(alert.to_message()))
            query.drop()

    def _ask_missing(self, seen: list[str]) -> None:
        """One query for every calibration when a device was seen without one (at most every REQUERY_S)."""
        now = time.monotonic()
        if now - self.asked < REQUERY_S or all(d in self.compass.calibrations for d in seen):
            return
        self.asked = now
        self.pending.append((now + 2.0, self._ask(2.0)))
