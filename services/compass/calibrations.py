"""The calibrations a compass applies: which are in force per device, which it refuses and why (not accepted by the
quality gate, not signed by a trusted key, older than the one in force), which devices are its shard's. No zenoh."""

from __future__ import annotations

import logging

import numpy as np

from magnet import signing, wire
from magnet.bounded import Recent
from magnet.shard import EVERY_DEVICE, Shard
from services.compass.watch import FleetWatch

log = logging.getLogger("magnet.compass")

MAX_REFUSED = 1024  # devices remembered for that between two asks (a flood beyond: one query for all)


class CalibrationsInForce:
    """Per-device state bounded by ``max_devices`` (calibrations in force, smoothing tails), the devices whose
    calibration was refused since the calibrators were last asked, the drop counters and the shard."""

    def __init__(
        self, trusted: signing.TrustedKeys | None, watch: FleetWatch, shard: Shard = EVERY_DEVICE, max_devices: int = 0
    ) -> None:
        self.trusted = trusted or signing.TrustedKeys()
        self.refused: set[str] = set()  # devices whose calibration was refused since the calibrators were last asked
        self.refused_overflow = False
        self.calibrations: Recent[str, wire.DeviceCalibration] = Recent(max_devices)
        self.tails: Recent[str, np.ndarray] = Recent(max_devices)
        self.max_devices = max_devices
        self._evictions_logged = False
        self.drops = wire.DropCounter()
        self.calibration_updates = 0
        self.watch = watch
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
        if current is not None and current.id == record.id and record.newer_than(current):
            self.calibrations[record.device] = record  # the same calibration again, renumbered (a rollback to it)
        elif current is None or current.id != record.id:
            self.calibrations[record.device] = record
            self.calibration_updates += 1
            self._log_evictions()
            self.watch.calibration(record, record.created_ns)
            self.calibration_changed(record.device)
            log.info("calibration %s (%s) in force for %s", record.id, record.calibration.method, record.device)
        return True

    def calibration_changed(self, device: str) -> None:
        """A new calibration is in force for ``device`` (what depends on the old one starts again)."""

    def applicable(self, record: wire.DeviceCalibration) -> None:
        """WireError unless ``record`` may be applied: accepted by the quality gate (its plausibility was checked
        when it was read), signed by a trusted key where keys are trusted, and newer than the one in force: a
        higher version, which the signature covers (``created_ns`` only between equal versions,
        ``DeviceCalibration.newer_than``)."""
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
        if current is not None and current.id != record.id and not record.newer_than(current):
            raise wire.WireError(
                "stale",
                f"calibration {record.id} (version {record.version}) of {record.device} is not newer than the one in "
                f"force ({current.id}, version {current.version})",
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

    def evicted_count(self) -> int:
        """Per-device entries forgotten for --max-devices: calibrations, tails, reported places, drift trackers."""
        return self.calibrations.evicted + self.tails.evicted + self.watch.evicted

    def _log_evictions(self) -> None:
        if not self._evictions_logged and self.evicted_count():
            self._evictions_logged = True
            log.warning(
                "more than %d devices: the least recently seen are forgotten (counted in status "
                "evicted_devices; raise --max-devices if they are genuine)",
                self.max_devices,
            )
