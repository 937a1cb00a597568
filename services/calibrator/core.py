"""The calibrator's core: per-device collections, the calibrations in force, the store, progress and status. No
zenoh inside: the shell (``services.calibrator.service``) feeds it raw batches and sends what it publishes.

Collection (``magnet.collection``) keeps samples evenly spread over the sphere (bounded by ``--max-samples``).
Without a session, a device that has no calibration is fitted whenever enough new cells filled and coverage reached
``--min-coverage``; the first fit the quality gate accepts is stored and published, and collection for it ends. An
operator's session (``services.calibrator.sessions``) collects afresh with its method and stores only on commit. A
rejected fit changes nothing: its reason goes out on ``calibration/progress``.
"""

from __future__ import annotations

import dataclasses
import logging
import time
from collections.abc import Callable
from typing import Any

import numpy as np

from magnet import signing, wire
from magnet.bounded import Recent
from magnet.collection import Collection
from magnet.model import Calibration
from magnet.quality import Coverage
from magnet.shard import EVERY_DEVICE, Shard
from services.calibrator import signatures
from services.calibrator.fleet import FleetBook
from services.calibrator.sessions import ACTIONS
from services.calibrator.settings import CalibratorSettings
from services.calibrator.status import CalibratorStatus, Counters, State
from services.calibrator.store import CalibrationStore

log = logging.getLogger("magnet.calibrator")

PROGRESS_INTERVAL_S = 0.5


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
        self.active = True  # False while another calibrator of the shard holds the lease: nothing collected, stored
        self.counters = Counters()
        self.unverified: set[str] = set()  # devices whose record in force this calibrator's key does not verify
        self.in_force = self._read_in_force()
        self.collections: Recent[str, Collection] = Recent(settings.max_devices, keep=lambda c: c.session)
        self.session_by: dict[str, str] = {}  # device -> who asked for its session's last action (``by``)
        self.last_progress: Recent[str, float] = Recent(settings.max_devices)
        self.drops = wire.DropCounter()

    def _read_in_force(self) -> dict[str, wire.DeviceCalibration]:
        """The records in force of this shard's devices, exactly as the store holds them now: served with the
        signature they were given when they were made, never signed here. With a signing key, the ones its key does
        not verify are counted in status ``unverified_records`` and logged (``signatures.unverified``): compasses
        with ``--trust`` refuse them."""
        in_force = {d: r for d, r in self.store.all_latest().items() if self.shard.owns(d)}
        if self.signer is not None:
            previous = getattr(self, "in_force", {})
            self.unverified = signatures.unverified(self.signer, in_force, previous, self.unverified)
            self.counters.unverified_records = len(self.unverified)
        return in_force

    # ------------------------------------------------------------------------------------------------- lease
    def publish_in_force(self) -> None:
        """Publish every record in force (when it starts or takes over: compasses may have missed them)."""
        for device, record in self.in_force.items():
            self.publish(wire.Kind.CALIBRATION, device, wire.pack(record.to_record()))

    def take_over(self) -> None:
        """Become the active calibrator of the shard: the records in force read back from the shared store (the
        calibrator that held the lease stored since), published, and collection starts."""
        try:
            self.in_force = self._read_in_force()
        except OSError as exc:  # a damaged store: serve what was read last, say so
            log.error("taking over: %s", exc)
        self.active = True
        self.counters.takeovers += 1
        self.publish_in_force()

    def stand_by(self) -> None:
        """Another calibrator holds the lease: stop collecting (sessions in progress are dropped, logged)."""
        sessions = [d for d, c in self.collections.items() if c.session]
        if sessions:
            log.warning("standing by: sessions of %s dropped (start them again)", ", ".join(sorted(sessions)))
        self.active = False
        self.collections.clear()

    # ------------------------------------------------------------------------------------------------ raw data
    def state(self, device: str) -> State:
        collection = self.collections.get(device)
        if collection is not None:
            return State.SESSION if collection.session else State.COLLECTING
        return State.CALIBRATED if device in self.in_force else State.IDLE

    def known(self, device: str) -> bool:
        """Whether ``device`` sent raw samples, has a calibration stored or is in the fleet file."""
        return (
            device in self.in_force
            or device in self.collections
            or device in self.fleet.last_seen_ns
            or device in self.fleet.places.fleet
        )

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
        if not self.active:
            return  # standing by: the active calibrator of the shard collects
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
        result = self.fit_collection(collection, now, device)
        if result is not None and not collection.session:
            try:
                self.commit(device, result)
            except OSError as exc:  # the store failed: nothing changed, collection goes on and tries again
                collection.last_reason = f"not stored: {exc}"
                if self.drops.count("store:write-failed"):
                    log.error("%s: %s", device, exc)
        elif result is None:
            log.info("%s: fit not accepted: %s", device, collection.last_reason)

    def fit_collection(self, collection: Collection, now: float, device: str | None = None) -> Calibration | None:
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
    def made_here(self, record: wire.DeviceCalibration) -> bool:
        """Whether ``record`` verifies under this calibrator's own key (always True without a key): what a rollback
        may put back in force, so that a rollback never gives a signature to a row it did not make."""
        return signatures.made_by(self.signer, record)

    def commit(
        self, device: str, calibration: Calibration, change: dict[str, Any] | None = None
    ) -> wire.DeviceCalibration:
        """Store ``calibration`` as the one in force for ``device`` (numbered one more than the highest version the
        store holds for it, signed), publish it, end collection. ``change`` (action, by, ...; default: an automatic
        or session calibration) is recorded beside it with when and from which id."""
        created_ns = self.clock_ns()
        previous = self.in_force.get(device)
        collection = self.collections.get(device)
        change = {
            "action": "session" if collection is not None and collection.session else "auto",
            "by": self.session_by.get(device, "") if collection is not None and collection.session else "",
            **(change or {}),
            "at_ns": created_ns,
            "from_id": previous.id if previous else None,
        }
        record, stored = self.store.append(
            device,
            lambda version: signatures.new_record(self.signer, device, created_ns, calibration, version),
            change,
            floor=previous.version if previous else 0,
        )
        if stored:
            self.counters.stored += 1
        self.in_force[device] = self.store.latest(device) or record
        if stored and device in self.unverified:  # its record in force is now one this calibrator made
            self.unverified.discard(device)
            self.counters.unverified_records = len(self.unverified)
        self.collections.pop(device, None)
        log.info(
            "%s: calibration %s version %d stored (%s, residual %s uT, coverage %s)",
            device,
            record.id,
            record.version,
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
    def session(self, device: str, action: str, method: str | None, by: str | None = None) -> dict[str, Any]:
        """Run a session action; returns the reply map ``{ok, action, state, message, progress, calibration?}``.
        ``by``: who asks (user@host, or the dashboard's operator), recorded with a commit."""
        handler = ACTIONS.get(action)
        if handler is None:
            raise ValueError(f"unknown action {action!r}: use one of {', '.join(ACTIONS)}")
        if by:
            self.session_by[device] = str(by)[:128]
        ok, message, extra = handler(self, device, method)
        collection = self.collections.get(device)
        if collection is None or not collection.session:  # no session open: nothing to remember (bounded)
            self.session_by.pop(device, None)
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
            dataclasses.replace(self.counters, forgotten_devices=self.fleet.forgotten),
            {s.value: states.count(s.value) for s in State},
            dict(self.drops.counts),
            str(self.shard),
            "active" if self.active else "standby",
        )
