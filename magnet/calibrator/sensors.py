"""Which sensor stands behind each device (hardware ids, docs/mavlink.md): the calibrator's memory of the sensor a
device's batches last named, whether a record in force is that sensor's, and, for a device whose record is another
sensor's, the newest record of its history made for the sensor now there (a compass missing at one boot and back at
the next). Pure: the core (``magnet.calibrator.core``) ends collections, commits and logs."""

from __future__ import annotations

import logging

from magnet import wire
from magnet.bounded import Recent
from magnet.calibrator.records import Records
from magnet.calibrator.rollback import ROLLBACK_DEPTH

log = logging.getLogger("magnet.calibrator")


class Sensors:
    """Per device the hardware id its batches last named (``last``) and the sensor last looked for in its history
    (``looked``: once per device and sensor); ``changes`` and ``back`` count sensor changes and records put back."""

    def __init__(self, max_devices: int) -> None:
        self.last: Recent[str, int] = Recent(max_devices)
        self.looked: Recent[str, int] = Recent(max_devices)
        self.changes = 0
        self.back = 0

    def changed(self, batch: wire.RawBatch) -> bool:
        """Note the sensor ``batch`` names (none: nothing noted); True when its device's sensor changed."""
        if not batch.hardware_id:
            return False
        before = self.last.get(batch.device)
        self.last[batch.device] = batch.hardware_id
        if before is None or before == batch.hardware_id:
            return False
        self.changes += 1
        log.warning(
            "%s: its sensor changed from %d to %d (a compass missing at boot?): collection started again",
            batch.device,
            before,
            batch.hardware_id,
        )
        return True

    @staticmethod
    def matches(record: wire.DeviceCalibration | None, batch: wire.RawBatch) -> bool:
        """Whether ``record`` (the device's in force, or None) is for ``batch``'s sensor (a record or a batch
        without an id counts as that sensor's)."""
        if record is None:
            return False
        wanted = record.calibration.hardware_id
        return wanted is None or not batch.hardware_id or wanted == batch.hardware_id

    def record_back(self, records: Records, batch: wire.RawBatch) -> wire.DeviceCalibration | None:
        """For a device whose record in force is another sensor's: the newest accepted record of its history made
        here for ``batch``'s sensor, looked for once per device and sensor; None otherwise. OSError when the store
        cannot be read."""
        device, sensor = batch.device, batch.hardware_id
        if self.matches(records.get(device), batch) or records.get(device) is None:
            return None
        if self.looked.get(device) == sensor:
            return None
        self.looked[device] = sensor
        for record in records.store.history(device, limit=ROLLBACK_DEPTH):
            calibration = record.calibration
            if calibration.hardware_id == sensor and calibration.accepted and records.made_here(record):
                log.info("%s: sensor %d is back: its calibration %s is in force again", device, sensor, record.id)
                return record
        return None
