"""The calibrator's decisions in one object, the compass's shape (``magnet.compass.CompassCore``): ``CalibratorCore``
with ``on_raw`` (a raw message in), ``commit`` (a calibration put in force), ``session`` and ``rollback`` (an
operator's actions), ``status`` (what it says of itself). It holds its parts and none of their logic:

- ``keys.ShardKeys`` and ``active`` (the lease, ``services.calibrator.lease``, is the service's): which devices it
  serves, and whether it holds the lease of its shard (only then does it collect, store and answer).
- ``collecting.Collections``: per-device sample buffers and their coverage.
- ``fitting.Fitter`` and ``records.Records``: fit and gate; sign, store and serve the records in force.
- ``sessions.Sessions`` and ``rollback``: an operator's actions.
- ``roster.Roster``: where each device is, when it was last seen, its open alerts.
- ``progress`` and ``status``: what it says about a device and about itself.

A raw batch (``on_raw``) is decoded, its device noted in the roster, its samples added to the device's collection;
a due collection that is ready is fitted, and an accepted automatic fit is signed, stored and published, which ends
its collection.

Hardware ids (docs/mavlink.md). A batch may name the sensor behind its device (``hardware_id``, as a MAVLink vehicle
reports it). Every record made carries the id of the sensor its samples came from; a collection whose device's sensor
changes (a compass missing at boot gave the instance to another) starts again, and a device whose record in force
names another sensor than its batches is collected as one without a calibration: the new sensor gets its own record,
and the other's is never fitted on, refreshed with or applied to samples that are not its own.

Pure: no zenoh, no database, no thread, no clock of its own. What it is given: a store (``store.CalibrationStore``,
the protocol the service's SQLite file implements), its settings (``settings.Settings``), where its messages go
(``publish(kind, device, payload_bytes)``), a monotonic clock (s) and a wall clock (ns since the epoch). The shell
(``services.calibrator.service``) feeds it and sends what it publishes.
"""

from __future__ import annotations

import dataclasses
import logging
from collections.abc import Callable
from typing import Any

from magnet import signing, wire
from magnet.calibration.collection import Collection
from magnet.calibrator.collecting import Collections
from magnet.calibrator.fitting import Fitter
from magnet.calibrator.keys import ShardKeys
from magnet.calibrator.progress import ProgressTimes, progress_of
from magnet.calibrator.records import Records
from magnet.calibrator.refresh import Refresher, gain_pct, small_gain
from magnet.calibrator.rollback import roll_back
from magnet.calibrator.roster import Roster
from magnet.calibrator.sensors import Sensors
from magnet.calibrator.sessions import Outcome, Sessions
from magnet.calibrator.settings import Settings
from magnet.calibrator.status import CalibratorStatus, Counters, IntakeFigures, State, devices_by_state, state_of
from magnet.calibrator.store import CalibrationStore
from magnet.model import Calibration
from magnet.shard import EVERY_DEVICE, Shard

log = logging.getLogger("magnet.calibrator")

Publish = Callable[[wire.Kind, str, bytes], None]


#: the session actions that store (or begin what a commit stores): refused while the store is gone, with the reason
_NEEDS_STORE = {"start": "started", "commit": "committed"}


class CalibratorCore:
    """The parts of a calibrator, wired (see the module docstring). ``clock``: monotonic seconds (when collections
    are due, progress intervals); ``clock_ns``: ns since the epoch (records' ``created_ns``, last seen)."""

    def __init__(
        self,
        store: CalibrationStore,
        settings: Settings,
        publish: Publish,
        clock: Callable[[], float],
        clock_ns: Callable[[], int],
        signer: signing.Signer | None = None,
        roster: Roster | None = None,
        shard: Shard = EVERY_DEVICE,
    ) -> None:
        self.settings, self.publish, self.clock, self.clock_ns, self.shard = settings, publish, clock, clock_ns, shard
        self.roster = roster if roster is not None else Roster()
        self.shard_keys = ShardKeys(shard)
        self.records = Records(store, signer, shard, clock_ns)
        self.collections = Collections(settings)
        self.fitter = Fitter(settings, self.roster.field_ut, self.roster.dip_deg, self.roster.declination_deg)
        self.refresher = Refresher(settings.recalibrate, settings.max_samples, settings.max_devices)
        self.sessions = Sessions(
            settings.method, self.collections, self.fitter, self.known, self.state, self.commit, clock
        )
        self.progress_times = ProgressTimes(settings.max_devices)
        self.active = True  # False while another calibrator of the shard holds the lease: nothing collected, stored
        self.takeovers = 0
        self.intake = IntakeFigures()  # set by the service loop
        self.drops = wire.DropCounter()
        self.sensors = Sensors(settings.max_devices)

    # ------------------------------------------------------------------------------------------------- lease
    def publish_in_force(self) -> None:
        """Publish every record in force (when it starts or takes over: compasses may have missed them)."""
        for device, record in self.records.in_force.items():
            self.publish(wire.Kind.CALIBRATION, device, wire.pack(record.to_record()))

    def take_over(self) -> None:
        """Become the active calibrator of the shard: the records in force read back from the shared store (the
        calibrator that held the lease stored since), published, and collection starts."""
        try:
            self.records.reload()
        except OSError as exc:  # a damaged store: serve what was read last, say so
            log.error("taking over: %s", exc)
        self.active = True
        self.takeovers += 1
        self.publish_in_force()

    def stand_by(self) -> None:
        """Another calibrator holds the lease: stop collecting (sessions in progress are dropped, logged)."""
        sessions = self.collections.clear()
        if sessions:
            log.warning("standing by: sessions of %s dropped (start them again)", ", ".join(sessions))
        self.active = False

    # ------------------------------------------------------------------------------------------------ raw data
    def on_raw(self, key_expr: str, payload: bytes, prefix: str) -> None:
        """One raw message (``<prefix>/<device>/raw``): collected, and fitted, stored and published when due."""
        if not self.active or not self.shard_keys.owns(key_expr, prefix):
            return  # standing by, or another shard's device
        try:
            batch = wire.decode_raw(payload, with_truth=False)
            wire.check_key(prefix, key_expr, wire.Kind.RAW, batch.device)
        except wire.WireError as exc:
            self.drops.drop(exc, "raw", log)
            return
        self.roster.seen(batch.device, batch.location, self.clock_ns())
        self._sensor(batch)
        collection = self.collections.receive(batch, self._calibrated(batch))
        if collection is None:
            self._refresh(batch)
            return
        now = self.clock()
        if collection.due(self.settings.min_samples, now) and self.collections.ready(collection, now):
            self._fitted(batch.device, collection, now)
        if self.progress_times.due(batch.device, now):
            self._report_progress(batch.device)

    def _sensor(self, batch: wire.RawBatch) -> None:
        """A device whose sensor changed: what was collected (another sensor's samples) ends, its refresh starts
        again; one whose record in force is another sensor's gets that sensor's record back when its history has one
        (``magnet.calibrator.sensors``)."""
        device = batch.device
        if self.sensors.changed(batch):
            if device in self.collections:
                self.collections.end(device)
            self.refresher.restart(device)
        try:
            target = self.sensors.record_back(self.records, batch)
            if target is not None:
                self.collections.end(device)
                self.commit(device, target.calibration, {"action": "sensor-back", "by": "", "to_id": target.id})
                self.sensors.back += 1
        except OSError as exc:
            log.error("%s: the record of sensor %d not put back: %s", device, batch.hardware_id, exc)

    def _calibrated(self, batch: wire.RawBatch) -> bool:
        """Whether the device has a record in force for this batch's sensor."""
        return self.sensors.matches(self.records.get(batch.device), batch)

    def _fitted(self, device: str, collection: Collection, now: float) -> None:
        """Fit a ready collection; an accepted automatic fit is stored (a session waits for its commit)."""
        result = self.fitter.fit(collection, now, device)
        if result is None:
            log.info("%s: fit not accepted: %s", device, collection.last_reason)
        elif not collection.session:
            try:
                self.commit(device, result)
            except OSError as exc:  # the store failed: nothing changed, collection goes on and tries again
                collection.last_reason = f"not stored: {exc}"
                if self.drops.count("store:write-failed"):
                    log.error("%s: %s", device, exc)

    def _refresh(self, batch: wire.RawBatch) -> None:
        """A calibrated device's batch: into its refresh collection, and when due fitted against the record in force
        (``magnet.calibrator.refresh``): committed (auto) or proposed as a session (propose) when better by the
        margin."""
        device, record = batch.device, self.records.get(batch.device)
        if not self._calibrated(batch):
            return  # the record in force is another sensor's
        collection = None if record is None else self.refresher.receive(batch, record.calibration)
        if record is None or collection is None or not self.refresher.due(collection, self.clock()):
            return
        self.refresher.fits += 1
        result = self.fitter.fit(collection, self.clock(), device, reference=record.calibration)
        why = collection.last_reason if result is None else small_gain(result)
        if result is None or why:
            log.info("%s: no refresh: %s", device, why)
            return
        gain = gain_pct(result)
        if self.refresher.proposes(collection, result):
            self.refresher.restart(device)
            self.collections.propose(device, collection)
            self.refresher.proposed += 1
            log.info("%s: refresh proposed (%.0f %% more consistent): commit it with a session", device, gain or 0)
            return
        alerts = self.roster.open_alerts(device)
        change = {"action": "refresh", "in_service": True, "gain_pct": gain, "resolves": alerts}
        try:
            self.commit(device, result, change)
        except OSError as exc:
            log.error("%s: refresh not stored: %s", device, exc)
            return
        self.refresher.restart(device)
        self.refresher.refreshed += 1
        if alerts:
            log.info("%s: in-service refresh made against drift alert(s) %s", device, ", ".join(alerts))

    def commit(
        self, device: str, calibration: Calibration, change: dict[str, Any] | None = None
    ) -> wire.DeviceCalibration:
        """Store ``calibration`` as the one in force for ``device`` (``records.store_new``: numbered, signed, with
        ``change``, by default an automatic calibration), publish it, end its collection; it names the sensor the
        device's batches last named unless it names one already. OSError: nothing changed."""
        sensor = self.sensors.last.get(device)
        if calibration.hardware_id is None and sensor:
            calibration = calibration.replace(hardware_id=sensor)
        record = self.records.store_new(device, calibration, {"action": "auto", "by": "", **(change or {})})
        self.collections.end(device)
        self.publish(wire.Kind.CALIBRATION, device, wire.pack(record.to_record()))
        self._report_progress(device)
        return record

    # ---------------------------------------------------------------------------------------- what it says
    def state(self, device: str) -> State:
        return state_of(self.collections.get(device), device in self.records.in_force)

    def known(self, device: str) -> bool:
        """Whether ``device`` sent raw samples, has a calibration stored or is in the fleet file."""
        return device in self.records.in_force or device in self.collections or self.roster.knows(device)

    def progress(self, device: str) -> wire.Progress:
        """Where the calibration of ``device`` stands."""
        return progress_of(
            self.state(device),
            self.clock_ns(),
            self.collections.get(device),
            self.records.get(device),
            self.settings.min_samples,
        )

    def _report_progress(self, device: str) -> None:
        self.progress_times.sent(device, self.clock())
        self.publish(wire.Kind.PROGRESS, device, wire.encode_progress(device, self.progress(device)))

    def session(self, device: str, action: str, method: str | None, by: str | None = None) -> dict[str, Any]:
        """Run a session action (``sessions.Sessions.act``); the reply map ``{ok, action, device, state, message,
        progress, calibration?}``. ValueError for an unknown action or method. While the store is gone
        (``store_gone``), a start or a commit is refused with the reason: nothing could be stored."""
        gone = self.store_gone()
        if gone is not None and action in _NEEDS_STORE:
            return self._reply(device, action, (False, f"not {_NEEDS_STORE[action]}: {gone}", {}))
        return self._reply(device, action, self.sessions.act(device, action, method, by))

    def store_gone(self) -> str | None:
        """Why the store can no longer take a record (its file deleted or replaced under it: the SQLite store's
        ``gone``), or None; a store without that check is never gone."""
        gone = getattr(self.records.store, "gone", None)
        return gone if isinstance(gone, str) else None

    def rollback(self, device: str, to_id: str | None, by: str | None) -> dict[str, Any]:
        """Put an earlier calibration back in force (``rollback.roll_back``); the reply map, as ``session``'s."""
        gone = self.store_gone()
        if gone is not None:
            return self._reply(device, "rollback", (False, f"not rolled back: {gone}", {}))
        return self._reply(device, "rollback", roll_back(self.records, self.commit, device, to_id, by))

    def _reply(self, device: str, action: str, outcome: Outcome) -> dict[str, Any]:
        ok, message, extra = outcome
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
        """The answer of ``<prefix>/@status/<name>``: each part's figures."""
        collections, fitter, records = self.collections, self.fitter, self.records
        counters = Counters(
            received_batches=collections.received_batches,
            received_samples=collections.received_samples,
            fits=fitter.fits,
            accepted=fitter.accepted,
            rejected=fitter.rejected,
            stored=records.stored,
            evicted_devices=collections.evicted,
            no_gyroscope=collections.no_gyroscope,
            forgotten_devices=self.roster.forgotten,
            takeovers=self.takeovers,
            refresh_fits=self.refresher.fits,
            refreshed=self.refresher.refreshed,
            proposed=self.refresher.proposed,
            unverified_records=len(records.unverified),
            sensor_changes=self.sensors.changes,
            sensors_back=self.sensors.back,
            **dataclasses.asdict(self.intake),
        )
        states = [self.state(d) for d in set(collections) | set(records.in_force)]
        return CalibratorStatus(
            name,
            counters,
            devices_by_state(states),
            dict(self.drops.counts),
            str(self.shard),
            "active" if self.active else "standby",
            store_problem=self.store_gone(),
        )
