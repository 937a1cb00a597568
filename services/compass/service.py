"""``magnet compass``: apply each device's calibration to its raw batches, tilt-compensate with the accelerometer, add
the WMM declination, and publish one heading message per raw batch on ``<prefix>/<device>/heading``.

On start it queries every stored calibration (``<prefix>/*/calibration``) and then follows new ones (subscriber);
a device with none is asked for again now and then, and meanwhile gets headings from its raw field (flag
CALIBRATED clear). Zenoh delivers into channels; this process's own loop drains them, decodes, computes a whole
drain of batches at once (vectorized over every sample of every device) and publishes, never inside a callback.
Counters (received, published, dropped by cause) answer on ``<prefix>/@status/<name>``.
"""

from __future__ import annotations

import argparse
import dataclasses
import logging
import time
from typing import Any

import numpy as np

from magnet import heading as hd
from magnet import wire
from magnet.model import Calibration
from services.common.zenoh_session import add_zenoh_arguments, drain, open_session, payload_bytes, stop_event

log = logging.getLogger("magnet.compass")

MAX_DRAIN = 4000          # raw messages computed together at most
CHANNEL_CAPACITY = 65536  # raw messages queued between zenoh and this loop
REQUERY_S = 5.0           # how often to ask again for the calibration of a device that has none
IDLE_SLEEP_S = 0.0003
_ZERO3, _EYE3 = np.zeros(3), np.eye(3)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--location", help="LAT,LON[,ALT_M] for the WMM declination and expected field "
                                           "(without it: declination 0, no field/dip disturbance check)")
    parser.add_argument("--date", help="date for the WMM (YYYY-MM-DD; default today)")
    parser.add_argument("--window", type=int, default=1, help="circular sliding mean over N headings (default 1)")
    parser.add_argument("--name", default="compass", help="service name for liveliness and status (default compass)")
    parser.add_argument("--devices", default="*",
                        help="key expression of the devices this instance serves (default *, all); e.g. 'line-1-*'")
    add_zenoh_arguments(parser)


@dataclasses.dataclass(frozen=True)
class Earth:
    """What the compass expects at its location: declination (deg, east +), |B| (uT), dip (deg); None = unknown."""

    declination_deg: float = 0.0
    total_ut: float | None = None
    inclination_deg: float | None = None

    @classmethod
    def from_args(cls, location: str | None, date: str | None) -> "Earth":
        if not location:
            return cls()
        from magnet.geomag import earth_field, parse_location

        lat, lon, alt = parse_location(location)
        field = earth_field(lat, lon, alt, date)
        return cls(field.declination_deg, field.total_ut, field.inclination_deg)


@dataclasses.dataclass(frozen=True)
class DeviceCalibration:
    id: str
    calibration: Calibration


def compute_headings(mag_ut: np.ndarray, acc_ms2: np.ndarray, offsets: np.ndarray, matrices: np.ndarray,
                     calibrated: np.ndarray, earth: Earth) -> dict[str, np.ndarray]:
    """Headings for S samples of any devices at once.

    mag_ut (S, 3) raw uT; acc_ms2 (S, 3) m/s^2 with NaN rows where a sample has no accelerometer; offsets (S, 3) and
    matrices (S, 3, 3) the calibration of each sample's device (B = A (u - b), see ``magnet.model``); calibrated (S,)
    bool. Returns field_ut (S, 3), heading_deg (magnetic), pitch_deg, roll_deg (0 without acc), flags (S,) int.
    """
    field = np.einsum("sij,sj->si", matrices, mag_ut - offsets)
    has_acc = np.isfinite(acc_ms2).all(axis=1)
    with np.errstate(invalid="ignore", divide="ignore"):
        tilted = hd.tilt_compensated_heading_deg(field, acc_ms2)
        pitch, roll = hd.pitch_roll_deg(acc_ms2)
    heading = np.where(has_acc & np.isfinite(tilted), tilted, hd.level_heading_deg(field))
    flags = hd.disturbance_flags(field, acc_ms2, earth.total_ut, earth.inclination_deg)
    flags |= np.where(calibrated, int(hd.HeadingFlag.CALIBRATED), 0)
    return {"field_ut": field, "heading_deg": heading, "pitch_deg": np.where(has_acc, pitch, 0.0),
            "roll_deg": np.where(has_acc, roll, 0.0), "flags": flags}


class Compass:
    """State of the compass loop: calibrations in force, smoothing tails, counters. No zenoh inside."""

    def __init__(self, earth: Earth, window: int) -> None:
        if window < 1:
            raise ValueError(f"--window must be >= 1, got {window}")
        self.earth = earth
        self.window = window
        self.calibrations: dict[str, DeviceCalibration] = {}
        self.tails: dict[str, np.ndarray] = {}
        self.drops = wire.DropCounter()
        self.received_batches = self.received_samples = self.published_batches = 0
        self.calibration_updates = 0
        self._key_devices: dict[str, str] = {}

    def accept_calibration(self, payload: bytes, key_expr: str, prefix: str) -> None:
        try:
            message = wire.decode_calibration(payload)
            wire.check_key(prefix, key_expr, wire.Kind.CALIBRATION, message.device)
        except wire.WireError as exc:
            self.drops.drop(exc, "calibration", log)
            return
        current = self.calibrations.get(message.device)
        if current is None or current.id != message.id:
            self.calibrations[message.device] = DeviceCalibration(message.id, message.calibration)
            self.calibration_updates += 1
            log.info("calibration %s (%s) in force for %s", message.id, message.calibration.method, message.device)

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
        mismatch = np.array([self._key_device(key, prefix) != device for key, device in zip(keys, columns.devices)],
                            dtype=bool)
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

    def compute(self, columns: wire.RawColumns) -> dict[str, Any]:
        """Heading columns for every sample of ``columns`` (see ``compute_headings``) plus ``true_heading_deg`` and
        ``calibration_ids`` (one per batch); counts what it received."""
        cals = [self.calibrations.get(device) for device in columns.devices]
        counts = columns.counts
        offsets = np.repeat(np.array([c.calibration.offset if c else _ZERO3 for c in cals]).reshape(-1, 3), counts,
                            axis=0)
        matrices = np.repeat(np.array([c.calibration.matrix if c else _EYE3 for c in cals]).reshape(-1, 3, 3),
                             counts, axis=0)
        calibrated = np.repeat(np.array([c is not None for c in cals], dtype=bool), counts)
        out = compute_headings(columns.mag_ut, columns.acc_ms2, offsets, matrices, calibrated, self.earth)
        self.received_batches += len(columns.devices)
        self.received_samples += int(counts.sum())
        if self.window > 1:
            bounds = np.concatenate([[0], np.cumsum(counts)])
            out["heading_deg"] = np.concatenate(
                [self._smooth(device, out["heading_deg"][bounds[i]:bounds[i + 1]])
                 for i, device in enumerate(columns.devices)] or [np.empty(0)])
        out["true_heading_deg"] = hd.true_heading_deg(out["heading_deg"], self.earth.declination_deg)
        out["calibration_ids"] = [c.id if c else "" for c in cals]
        return out

    def encode(self, columns: wire.RawColumns) -> list[bytes]:
        """One heading payload per raw batch of ``columns``, in order."""
        out = self.compute(columns)
        return wire.encode_headings(columns, out["heading_deg"], out["true_heading_deg"], out["pitch_deg"],
                                    out["roll_deg"], out["field_ut"], out["flags"], self.earth.declination_deg,
                                    out["calibration_ids"])

    def process(self, batches: list[wire.RawBatch]) -> list[wire.HeadingBatch]:
        """Heading batches, one per raw batch, computed in one vectorized pass."""
        if not batches:
            return []
        columns = wire.RawColumns.from_batches(batches)
        out = self.compute(columns)
        bounds = np.concatenate([[0], np.cumsum(columns.counts)]).tolist()
        return [wire.HeadingBatch(batch.device, batch.seq, batch.t_ns, *(out[name][lo:hi] for name in (
                    "heading_deg", "true_heading_deg", "pitch_deg", "roll_deg", "field_ut")),
                    self.earth.declination_deg, cal_id, out["flags"][lo:hi])
                for batch, cal_id, lo, hi in zip(batches, out["calibration_ids"], bounds[:-1], bounds[1:])]

    def _smooth(self, device: str, heading: np.ndarray) -> np.ndarray:
        if self.window == 1:
            return heading
        tail = self.tails.get(device, np.empty(0))
        joined = np.concatenate([tail, heading])
        self.tails[device] = joined[-(self.window - 1):]
        return hd.smooth_heading_deg(joined, self.window)[-heading.size:]

    def status(self, name: str) -> dict[str, Any]:
        return {"v": wire.WIRE_VERSION, "service": "compass", "name": name,
                "received_batches": self.received_batches, "received_samples": self.received_samples,
                "published_batches": self.published_batches, "calibrations": len(self.calibrations),
                "calibration_updates": self.calibration_updates, "dropped": dict(self.drops.counts),
                "dropped_total": self.drops.total}


def run(args: argparse.Namespace) -> int:
    import zenoh

    compass = Compass(Earth.from_args(args.location, args.date), args.window)
    stop = stop_event()
    prefix = args.prefix
    devices = args.devices
    with open_session(args) as session:
        token = session.liveliness().declare_token(wire.liveliness_key(prefix, "compass", args.name))
        raw_sub = session.declare_subscriber(f"{prefix}/{devices}/raw", zenoh.handlers.FifoChannel(CHANNEL_CAPACITY))
        cal_sub = session.declare_subscriber(f"{prefix}/{devices}/calibration", zenoh.handlers.FifoChannel(1024))
        status_q = session.declare_queryable(wire.status_key(prefix, args.name), zenoh.handlers.FifoChannel(64))
        heading_keys: dict[str, str] = {}
        pending: list[tuple[float, Any]] = [(time.monotonic() + 3.0, session.get(f"{prefix}/{devices}/calibration",
                                                                                    timeout=3.0))]
        asked: dict[str, float] = {"*": time.monotonic()}
        log.info("compass %s: serving %s/%s, declination %.2f deg", args.name, prefix, devices,
                 compass.earth.declination_deg)
        while not stop.is_set():
            busy = False
            pending = _poll_replies(pending, compass, prefix)
            for sample in drain(cal_sub, 1000):
                compass.accept_calibration(payload_bytes(sample), str(sample.key_expr), prefix)
            for query in drain(status_q, 64):
                query.reply(wire.status_key(prefix, args.name), wire.pack(compass.status(args.name)))
                query.drop()  # finalize now: the asker waits for it
            samples = drain(raw_sub, MAX_DRAIN)
            if samples:
                busy = True
                columns = compass.decode_columns([(str(s.key_expr), s.payload.to_bytes()) for s in samples], prefix)
                for device, payload in zip(columns.devices, compass.encode(columns)):
                    key = heading_keys.get(device) or heading_keys.setdefault(
                        device, wire.key(prefix, device, wire.Kind.HEADING))
                    session.put(key, payload)  # measured: a declared publisher per device costs ~5x the CPU
                    compass.published_batches += 1
                pending += _ask_missing(session, compass, columns.devices, asked, prefix, devices)
            if not busy:
                time.sleep(IDLE_SLEEP_S)
        token.undeclare()
    log.info("compass stopped: %s", compass.status(args.name))
    return 0


def _poll_replies(pending: list[tuple[float, Any]], compass: Compass, prefix: str) -> list[tuple[float, Any]]:
    """Take the replies of calibration queries that arrived; keep the queries that may still answer."""
    still = []
    now = time.monotonic()
    for deadline, handler in pending:
        for reply in drain(handler, 10_000):
            if reply.ok is not None:
                compass.accept_calibration(payload_bytes(reply.ok), str(reply.ok.key_expr), prefix)
        if now < deadline:
            still.append((deadline, handler))
    return still


def _ask_missing(session: Any, compass: Compass, seen: list[str], asked: dict[str, float],
                 prefix: str, devices: str) -> list[tuple[float, Any]]:
    """One query for every calibration when a device was seen without one (at most every REQUERY_S)."""
    now = time.monotonic()
    if now - asked.get("*", now) < REQUERY_S or all(d in compass.calibrations for d in seen):
        return []
    asked["*"] = now
    return [(now + 2.0, session.get(f"{prefix}/{devices}/calibration", timeout=2.0))]
