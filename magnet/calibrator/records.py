"""The records part of the calibrator: the calibrations in force of its shard's devices, as the store holds them, and
new ones signed (``magnet.calibrator.signatures``) and stored (any ``magnet.calibrator.store.CalibrationStore``). A
record is signed once, when it is made; read back it is served as stored. No zenoh inside: the composition publishes
what it stores.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from typing import Any

from magnet import signing, wire
from magnet.calibrator import signatures
from magnet.calibrator.store import CalibrationStore
from magnet.model import Calibration
from magnet.shard import EVERY_DEVICE, Shard

log = logging.getLogger("magnet.calibrator")


class Records:
    """The records in force (device -> ``wire.DeviceCalibration``) of ``shard``'s devices; ``signer`` signs what it
    stores (unsigned without one); ``clock_ns`` stamps them (ns since the epoch)."""

    def __init__(
        self,
        store: CalibrationStore,
        signer: signing.Signer | None = None,
        shard: Shard = EVERY_DEVICE,
        clock_ns: Callable[[], int] = lambda: 0,
    ) -> None:
        self.store, self.signer, self.shard, self.clock_ns = store, signer, shard, clock_ns
        self.stored = 0  # records stored since it started
        self.unverified: set[str] = set()  # devices whose record in force this calibrator's key does not verify
        self.in_force: dict[str, wire.DeviceCalibration] = {}
        self.reload()

    def reload(self) -> None:
        """Read the records in force back from the store (a takeover: another calibrator may have stored since);
        OSError when the store cannot be read, nothing changed. With a signing key, the ones its key does not verify
        are kept in ``unverified`` and logged (``signatures.unverified``): compasses with ``--trust`` refuse them."""
        in_force = {d: r for d, r in self.store.all_latest().items() if self.shard.owns(d)}
        if self.signer is not None:
            self.unverified = signatures.unverified(self.signer, in_force, self.in_force, self.unverified)
        self.in_force = in_force

    def get(self, device: str) -> wire.DeviceCalibration | None:
        return self.in_force.get(device)

    def made_here(self, record: wire.DeviceCalibration) -> bool:
        """Whether ``record`` verifies under this calibrator's own key (always True without a key): what a rollback
        may put back in force, so that a rollback never gives a signature to a row it did not make."""
        return signatures.made_by(self.signer, record)

    def store_new(self, device: str, calibration: Calibration, change: dict[str, Any]) -> wire.DeviceCalibration:
        """Store ``calibration`` as the one in force for ``device``, numbered one more than the highest version the
        store holds for it and signed; ``change`` (action, by, ...) is recorded beside it with when (``at_ns``) and
        from which id (``from_id``). The record now in force; OSError when the store cannot take it (nothing
        changed)."""
        created_ns = self.clock_ns()
        previous = self.in_force.get(device)
        change = {**change, "at_ns": created_ns, "from_id": previous.id if previous else None}
        record, stored = self.store.append(
            device,
            lambda version: signatures.new_record(self.signer, device, created_ns, calibration, version),
            change,
            floor=previous.version if previous else 0,
        )
        if stored:
            self.stored += 1
            self.unverified.discard(device)  # its record in force is now one this calibrator made
        self.in_force[device] = self.store.latest(device) or record
        log.info(
            "%s: calibration %s version %d stored (%s, residual %s uT, coverage %s)",
            device,
            record.id,
            record.version,
            calibration.method,
            calibration.quality.residual_rms_ut,
            calibration.quality.coverage,
        )
        return self.in_force[device]
