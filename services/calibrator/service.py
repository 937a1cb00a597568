"""``magnet calibrator``: collect raw samples per device, fit, gate, store (SQLite) and serve calibrations.

Collection (``magnet.collection``) keeps samples evenly spread over the sphere (bounded by ``--max-samples``).
Without a session, a device that has no calibration is fitted whenever enough new cells filled and coverage reached
``--min-coverage``; the first fit the quality gate accepts is stored and published, and collection for it ends. An
operator's session (``calibrate`` queryable: start / status / commit / abort) collects afresh with its method and
stores only on commit. A rejected fit changes nothing: its reason goes out on ``calibration/progress``.

Queryables: see ``services.calibrator.queries``. One thread: zenoh delivers into channels, this loop drains them.
"""

from __future__ import annotations

import argparse
import dataclasses
import enum
import logging
import os
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import zenoh

from magnet import signing, wire
from magnet.bounded import Recent
from magnet.calibration import Method
from magnet.collection import Collection
from magnet.fleet import Places
from magnet.geomag import earth_field, parse_location
from magnet.model import Calibration
from magnet.place import Location
from magnet.quality import Coverage
from magnet.shard import EVERY_DEVICE, Shard
from services.calibrator import queries
from services.calibrator.fleet import FleetBook
from services.calibrator.store import CalibrationStore
from services.common.fleet_options import add_fleet_argument, read_fleet
from services.common.zenoh_session import (
    ZenohSettings,
    add_zenoh_arguments,
    drain,
    open_session,
    payload_bytes,
    stop_event,
)

log = logging.getLogger("magnet.calibrator")

PROGRESS_INTERVAL_S = 0.5
DEFAULT_MAX_DEVICES = 10_000
CHANNEL_CAPACITY = 65536
IDLE_SLEEP_S = 0.0005


def default_db_path() -> Path:
    base = Path(os.environ.get("XDG_DATA_HOME", Path.home() / ".local" / "share"))
    return base / "magnet" / "calibrations.db"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--db", type=Path, default=None, help=f"SQLite file (default {default_db_path()})")
    parser.add_argument(
        "--method",
        default="ellipsoid",
        help="fit method for automatic calibration (default ellipsoid; sessions may choose another)",
    )
    parser.add_argument("--location", help="LAT,LON[,ALT_M]: scale fits to the WMM field strength there")
    parser.add_argument("--field-ut", type=float, help="expected field strength in uT (instead of --location)")
    parser.add_argument(
        "--min-coverage", type=float, default=0.8, help="sphere coverage before an automatic fit is tried (default 0.8)"
    )
    parser.add_argument("--min-samples", type=int, default=150, help="kept samples before a fit (default 150)")
    parser.add_argument("--max-samples", type=int, default=1500, help="kept samples per device at most")
    parser.add_argument("--no-auto", action="store_true", help="calibrate only in operator sessions")
    parser.add_argument("--name", default="calibrator", help="service name for liveliness and status")
    parser.add_argument("--devices", default="*", help="key expression of the devices served (default *)")
    parser.add_argument(
        "--max-devices",
        type=int,
        default=DEFAULT_MAX_DEVICES,
        help="devices collected at once at most; beyond, the least recently seen automatic collection "
        f"is dropped (sessions stay) (default {DEFAULT_MAX_DEVICES})",
    )
    add_fleet_argument(parser)
    parser.add_argument(
        "--signing-key",
        type=Path,
        metavar="FILE.key",
        help="sign every calibration it serves with this Ed25519 private key (`magnet keys`); "
        "compasses started with --trust FILE.pub apply only those",
    )
    parser.add_argument(
        "--shard",
        default="0/1",
        metavar="K/N",
        help="collect, fit, store and answer only for the devices of shard K of N (0 <= K < N; see "
        "magnet.shard); default 0/1, every device",
    )
    add_zenoh_arguments(parser)


@dataclasses.dataclass(frozen=True)
class CalibratorSettings:
    """How the calibrator fits: method, expected |B| (uT or None), coverage and sample counts, automatic or not."""

    method: str = "ellipsoid"
    field_ut: float | None = None
    min_coverage: float = 0.8
    min_samples: int = 150
    max_samples: int = 1500
    auto: bool = True
    max_devices: int = DEFAULT_MAX_DEVICES

    def __post_init__(self) -> None:
        Method.parse(self.method)
        if not 0 <= self.min_coverage <= 1:
            raise ValueError(f"--min-coverage must be a fraction in [0, 1], got {self.min_coverage}")
        if not 30 <= self.min_samples <= self.max_samples:
            raise ValueError(f"need 30 <= --min-samples <= --max-samples, got {self.min_samples}, {self.max_samples}")
        if self.field_ut is not None and not 1 <= self.field_ut <= 1000:
            raise ValueError(f"--field-ut must be a field strength in uT (1..1000), got {self.field_ut}")
        if isinstance(self.max_devices, bool) or not isinstance(self.max_devices, int) or self.max_devices < 1:
            raise ValueError(f"--max-devices must be a whole number >= 1, got {self.max_devices}")


@dataclasses.dataclass(frozen=True)
class ServiceSettings:
    """Everything ``magnet calibrator`` runs with: the fit settings, the database, its name, the devices it serves
    (a key expression chunk) and the Zenoh options."""

    fitting: CalibratorSettings
    db: Path
    name: str = "calibrator"
    devices: str = "*"
    zenoh: ZenohSettings = ZenohSettings()
    signing_key: Path | None = None
    places: Places | None = None  # --fleet file and --location: each device's expected field
    shard: Shard = EVERY_DEVICE


def settings_from_args(args: argparse.Namespace) -> ServiceSettings:
    field_ut = args.field_ut
    if field_ut is None and args.location:
        field_ut = earth_field(*parse_location(args.location)).total_ut
    fitting = CalibratorSettings(
        method=args.method,
        field_ut=field_ut,
        min_coverage=args.min_coverage,
        min_samples=args.min_samples,
        max_samples=args.max_samples,
        auto=not args.no_auto,
        max_devices=args.max_devices,
    )
    places = Places(read_fleet(args.fleet), Location.parse(args.location) if args.location else None)
    return ServiceSettings(
        fitting,
        args.db or default_db_path(),
        args.name,
        args.devices,
        ZenohSettings.from_args(args),
        args.signing_key,
        places,
        Shard.parse(args.shard),
    )


def load_signer(path: Path | None) -> signing.Signer | None:
    """The signer of ``--signing-key`` (None without one); OSError/ValueError naming a file that cannot be used."""
    if path is None:
        return None
    if path.stat().st_mode & 0o077:
        log.warning("signing key %s is readable by others: chmod 600 it", path)
    return signing.Signer(signing.load_private_key(path.read_bytes(), str(path)))


class State(enum.Enum):
    COLLECTING = "collecting"  # automatic collection (device has no calibration)
    SESSION = "session"  # an operator's calibration session
    CALIBRATED = "calibrated"  # a calibration is in force, nothing collected
    IDLE = "idle"  # no calibration, automatic calibration off


@dataclasses.dataclass
class Counters:
    """What the calibrator did since it started."""

    received_batches: int = 0
    received_samples: int = 0
    fits: int = 0
    accepted: int = 0
    rejected: int = 0
    stored: int = 0
    evicted_devices: int = 0  # collections dropped for --max-devices


@dataclasses.dataclass(frozen=True)
class CalibratorStatus:
    """The answer of ``<prefix>/@status/<name>``: counters, devices per state, drops by cause."""

    name: str
    counters: Counters
    devices: dict[str, int]
    dropped: dict[str, int]
    shard: str = "0/1"

    def to_dict(self) -> dict[str, Any]:
        return {
            "v": wire.WIRE_VERSION,
            "service": "calibrator",
            "name": self.name,
            **dataclasses.asdict(self.counters),
            "devices": dict(self.devices),
            "dropped": dict(self.dropped),
            "dropped_total": sum(self.dropped.values()),
            "shard": self.shard,
        }


#: a session action: (calibrator, device, method) -> (ok, message, extra reply fields)
Action = Callable[["Calibrator", str, "str | None"], "tuple[bool, str, dict[str, Any]]"]


class Calibrator:
    """Per-device collections, the calibrations in force, the store; no zenoh inside (``publish`` is injected:
    ``publish(kind, device, payload_bytes)``)."""

    def __init__(
        self,
        store: CalibrationStore,
        settings: CalibratorSettings,
        publish: Callable[[wire.Kind, str, bytes], None],
        clock: Callable[[], float] = time.monotonic,
        clock_ns: Callable[[], int] = time.time_ns,
        signer: signing.Signer | None = None,
        fleet: FleetBook | None = None,
        shard: Shard = EVERY_DEVICE,
    ) -> None:
        self.store, self.settings, self.publish = store, settings, publish
        self.fleet = fleet if fleet is not None else FleetBook()
        self.clock, self.clock_ns = clock, clock_ns
        self.signer = signer
        self.shard = shard  # only this shard's devices: collected, fitted, stored, answered
        self._mine: dict[str, bool] = {}
        self.in_force: dict[str, wire.DeviceCalibration] = {
            d: self.sign(r) for d, r in store.all_latest().items() if shard.owns(d)
        }
        self.collections: Recent[str, Collection] = Recent(settings.max_devices, keep=lambda c: c.session)
        self.last_progress: Recent[str, float] = Recent(settings.max_devices)
        self.drops = wire.DropCounter()
        self.counters = Counters()

    # ------------------------------------------------------------------------------------------------ raw data
    def state(self, device: str) -> State:
        collection = self.collections.get(device)
        if collection is not None:
            return State.SESSION if collection.session else State.COLLECTING
        return State.CALIBRATED if device in self.in_force else State.IDLE

    def mine(self, key_expr: str, prefix: str) -> bool:
        """Whether the device of a raw key belongs to this shard (a malformed key: True, to be refused and counted)."""
        owned = self._mine.get(key_expr)
        if owned is None:
            try:
                owned = self.shard.owns(wire.device_from_key(prefix, key_expr, wire.Kind.RAW))
            except wire.WireError:
                return True
            if len(self._mine) < 200_000:
                self._mine[key_expr] = owned
        return owned

    def on_raw(self, key_expr: str, payload: bytes, prefix: str) -> None:
        if not self.shard.everything and not self.mine(key_expr, prefix):
            return  # another shard's device
        try:
            batch = wire.decode_raw(payload, with_truth=False)
            wire.check_key(prefix, key_expr, wire.Kind.RAW, batch.device)
        except wire.WireError as exc:
            self.drops.drop(exc, "raw", log)
            return
        self.counters.received_batches += 1
        self.counters.received_samples += len(batch)
        self.fleet.seen(batch.device, batch.location, self.clock_ns())
        collection = self.collections.get(batch.device)
        if collection is None:
            if batch.device in self.in_force or not self.settings.auto:
                return
            collection = self.collections[batch.device] = Collection(
                self.settings.method, False, self.settings.max_samples
            )
            self._evictions()
        self.collections.touch(batch.device)
        collection.add(batch.mag_ut, batch.acc_ms2)
        now = self.clock()
        if collection.due(self.settings.min_samples, now):
            self._try(batch.device, collection, now)
        if now - self.last_progress.get(batch.device, -np.inf) >= PROGRESS_INTERVAL_S:
            self._progress(batch.device)

    def _evictions(self) -> None:
        """Count collections dropped for the --max-devices bound (logged the first time)."""
        evicted = self.collections.evicted
        if evicted > self.counters.evicted_devices:
            if not self.counters.evicted_devices:
                log.warning(
                    "more than %d devices collecting at once: the least recently seen are dropped (counted "
                    "in status evicted_devices; raise --max-devices if they are genuine)",
                    self.settings.max_devices,
                )
            self.counters.evicted_devices = evicted

    def _try(self, device: str, collection: Collection, now: float) -> None:
        cov = collection.coverage()
        if not collection.session and cov.fraction < self.settings.min_coverage:
            collection.last_reason = (
                f"coverage {cov.fraction:.0%} below {self.settings.min_coverage:.0%}: "
                f"{', '.join(cov.missing) or 'move through more attitudes'}"
            )
            collection.last_fit_kept, collection.last_fit_s = collection.kept, now
            return
        result = self._fit(collection, now, device)
        if result is not None and not collection.session:
            try:
                self.commit(device, result)
            except OSError as exc:  # the store failed: nothing changed, collection goes on and tries again
                collection.last_reason = f"not stored: {exc}"
                if self.drops.count("store:write-failed"):
                    log.error("%s: %s", device, exc)
        elif result is None:
            log.info("%s: fit not accepted: %s", device, collection.last_reason)

    def _fit(self, collection: Collection, now: float, device: str | None = None) -> Calibration | None:
        """Fit the collection (scaled to the WMM |B| at the device's place when known) and count it; the
        calibration when the gate accepts it, else None."""
        field_ut = (self.fleet.field_ut(device) if device else None) or self.settings.field_ut
        result = collection.fit(field_ut, now)
        self.counters.fits += 1
        accepted = result is not None and result.accepted
        if accepted:
            self.counters.accepted += 1
        else:
            self.counters.rejected += 1
        return result if accepted else None

    # ---------------------------------------------------------------------------------------------- storing
    def sign(self, record: wire.DeviceCalibration) -> wire.DeviceCalibration:
        """``record`` signed with this calibrator's key (unchanged without one): its own store is trusted."""
        if self.signer is None:
            return record
        signed = self.signer.sign(record.to_record())
        return dataclasses.replace(record, sig=signed["sig"], key_id=signed["key_id"])

    def commit(
        self, device: str, calibration: Calibration, change: dict[str, Any] | None = None
    ) -> wire.DeviceCalibration:
        """Store ``calibration`` as the one in force for ``device``, publish it, end collection. ``change`` (action,
        by, ...; default: an automatic or session calibration) is recorded beside it with when and from which id."""
        record = self.sign(wire.DeviceCalibration(device, self.clock_ns(), calibration))
        previous = self.in_force.get(device)
        collection = self.collections.get(device)
        change = {
            "action": "session" if collection is not None and collection.session else "auto",
            "by": "",
            **(change or {}),
            "at_ns": record.created_ns,
            "from_id": previous.id if previous else None,
        }
        if self.store.save(record, change):
            self.counters.stored += 1
        self.in_force[device] = self.sign(self.store.latest(device) or record)
        self.collections.pop(device, None)
        log.info(
            "%s: calibration %s stored (%s, residual %s uT, coverage %s)",
            device,
            record.id,
            calibration.method,
            calibration.quality.residual_rms_ut,
            calibration.quality.coverage,
        )
        self.publish(wire.Kind.CALIBRATION, device, wire.pack(self.in_force[device].to_record()))
        self._progress(device)
        return self.in_force[device]

    def progress(self, device: str) -> wire.Progress:
        """Where the calibration of ``device`` stands."""
        state, now = self.state(device).value, self.clock_ns()
        collection = self.collections.get(device)
        record = self.in_force.get(device)
        record_id = record.id if record else None
        if collection is None:
            if record is None:
                return wire.Progress(state, now, record_id)
            cal = record.calibration
            return wire.Progress(
                state,
                now,
                record_id,
                cal.method,
                cal.sample_count,
                cal.quality.coverage,
                (),
                cal.quality.residual_rms_ut,
                True,
                cal.reason,
            )
        cov = collection.coverage()
        last = collection.last_fit
        return wire.Progress(
            state,
            now,
            record_id,
            collection.method,
            collection.kept,
            cov.fraction,
            tuple(cov.missing),
            None if last is None else last.quality.residual_rms_ut,
            None if last is None else bool(last.accepted),
            collection.last_reason or self._waiting_reason(collection, cov),
            wire.Collecting(collection.session, collection.seen, cov.cells_hit, cov.cell_count),
        )

    def _waiting_reason(self, collection: Collection, cov: Coverage) -> str:
        advice = ", ".join(cov.missing) or "move through more attitudes"
        return (
            f"{collection.kept} of {self.settings.min_samples} evenly spread samples, coverage "
            f"{cov.fraction:.0%}: {advice}"
        )

    def _progress(self, device: str) -> None:
        self.last_progress[device] = self.clock()
        self.publish(wire.Kind.PROGRESS, device, wire.encode_progress(device, self.progress(device)))

    # ---------------------------------------------------------------------------------------------- sessions
    def session(self, device: str, action: str, method: str | None) -> dict[str, Any]:
        """Run a session action; returns the reply map ``{ok, action, state, message, progress, calibration?}``."""
        handler = ACTIONS.get(action)
        if handler is None:
            raise ValueError(f"unknown action {action!r}: use one of {', '.join(ACTIONS)}")
        ok, message, extra = handler(self, device, method)
        return {
            "ok": ok,
            "action": action,
            "device": device,
            "state": self.state(device).value,
            "message": message,
            "progress": self.progress(device).to_dict(),
            **extra,
        }

    def status(self, name: str) -> CalibratorStatus:
        states = [self.state(d).value for d in set(self.collections) | set(self.in_force)]
        return CalibratorStatus(
            name,
            dataclasses.replace(self.counters),
            {s.value: states.count(s.value) for s in State},
            dict(self.drops.counts),
            str(self.shard),
        )


def _start(calibrator: Calibrator, device: str, method: str | None) -> tuple[bool, str, dict[str, Any]]:
    chosen = Method.parse(method or calibrator.settings.method).value
    if chosen == Method.TURNTABLE.value:  # it needs each sample's known heading and the field's components
        return (
            False,
            (
                "a turntable calibration cannot be collected from live samples (it needs the turntable's "
                "headings and the field's components): record the turns and run `magnet fit --method "
                "turntable` on the file"
            ),
            {},
        )
    calibrator.collections[device] = Collection(chosen, True, calibrator.settings.max_samples)
    return True, f"session started with {chosen}: move the device through every attitude, then commit", {}


def _status(calibrator: Calibrator, device: str, method: str | None) -> tuple[bool, str, dict[str, Any]]:
    return True, calibrator.state(device).value, {}


def _commit(calibrator: Calibrator, device: str, method: str | None) -> tuple[bool, str, dict[str, Any]]:
    collection = calibrator.collections.get(device)
    if collection is None or not collection.session:
        return False, "no session to commit: start one first", {}
    result = calibrator._fit(collection, calibrator.clock(), device)
    if result is None:
        return False, f"not committed, the calibration in force stays: {collection.last_reason}", {}
    try:
        return True, "committed", {"calibration": calibrator.commit(device, result).to_record()}
    except OSError as exc:
        return False, f"not committed, the calibration in force stays: {exc}", {}


def _abort(calibrator: Calibrator, device: str, method: str | None) -> tuple[bool, str, dict[str, Any]]:
    collection = calibrator.collections.get(device)
    if collection is None or not collection.session:
        return False, "no session to abort", {}
    del calibrator.collections[device]
    return True, "session aborted; the calibration in force stays", {}


ACTIONS: dict[str, Action] = {"start": _start, "status": _status, "commit": _commit, "abort": _abort}


# ------------------------------------------------------------------------------------------------------- shell


def run_calibrator(args: argparse.Namespace) -> int:
    """``magnet calibrator``: the settings from the options, then ``run``."""
    return run(settings_from_args(args))


def run(settings: ServiceSettings) -> int:
    stop = stop_event()
    prefix, devices, name = settings.zenoh.prefix, settings.devices, settings.name
    signer = load_signer(settings.signing_key)  # a bad key file ends here, before anything is opened
    with CalibrationStore(settings.db) as store, open_session(settings.zenoh) as session:

        def publish(kind: wire.Kind, device: str, payload: bytes) -> None:
            # no declared publisher per device: a flood of new device ids would hold one each
            session.put(wire.key(prefix, device, kind), payload)

        calibrator = Calibrator(
            store, settings.fitting, publish, signer=signer, fleet=FleetBook(settings.places), shard=settings.shard
        )
        token = session.liveliness().declare_token(wire.liveliness_key(prefix, "calibrator", name))
        raw_sub = session.declare_subscriber(f"{prefix}/{devices}/raw", zenoh.handlers.FifoChannel(CHANNEL_CAPACITY))
        answers = [
            (
                queries.ANSWERS[kind],
                session.declare_queryable(f"{prefix}/{devices}/{kind.value}", zenoh.handlers.FifoChannel(256)),
            )
            for kind in queries.ANSWERS
        ]
        answers.append(
            (
                queries.status_answer(name),
                session.declare_queryable(wire.status_key(prefix, name), zenoh.handlers.FifoChannel(64)),
            )
        )
        answers.append(
            (queries.answer_fleet, session.declare_queryable(f"{prefix}/@fleet", zenoh.handlers.FifoChannel(16)))
        )
        alert_key = f"{prefix}/{devices}/{wire.Kind.ALERT.value}"
        feeds: list[tuple[Any, Callable[[str, bytes, str], None]]] = [
            (session.declare_subscriber(alert_key, zenoh.handlers.FifoChannel(4096)), calibrator.fleet.on_alert),
            (session.get(alert_key, timeout=3.0), calibrator.fleet.on_alert),
        ]  # the alerts open already
        for device, record in calibrator.in_force.items():
            publish(wire.Kind.CALIBRATION, device, wire.pack(record.to_record()))
        log.info(
            "calibrator %s (shard %s): %d calibration(s) in store %s",
            name,
            settings.shard,
            len(calibrator.in_force),
            store.path,
        )
        _loop(stop, calibrator, raw_sub, answers, prefix, feeds)
        token.undeclare()
    log.info("calibrator stopped: %s", calibrator.status(name).to_dict())
    return 0


def _loop(
    stop: Any,
    calibrator: Calibrator,
    raw_sub: Any,
    answers: list[tuple[Any, Any]],
    prefix: str,
    feeds: Sequence[tuple[Any, Callable[[str, bytes, str], None]]] = (),
) -> None:
    """Drain raw samples, queries and ``feeds`` (samples or replies -> handler(key, payload, prefix)) until
    ``stop`` is set."""
    while not stop.is_set():
        for handler, take in feeds:
            for item in drain(handler, 1000):
                sample = getattr(item, "ok", item)
                if sample is not None and hasattr(sample, "key_expr"):
                    take(str(sample.key_expr), payload_bytes(sample), prefix)
        samples = drain(raw_sub, 2000)
        for sample in samples:
            calibrator.on_raw(str(sample.key_expr), payload_bytes(sample), prefix)
        for answer, queryable in answers:
            for query in drain(queryable, 64):
                answer(query, calibrator, prefix)
                query.drop()  # finalize now: the asker waits for it
        if not samples:
            time.sleep(IDLE_SLEEP_S)
