"""The status part of the calibrator: the state of a device, the counters gathered from the other parts and the
answer of ``<prefix>/@status/<name>``. Imports none of the other parts: they hand it plain figures."""

from __future__ import annotations

import dataclasses
import enum
from typing import Any

from magnet import wire
from magnet.calibration.collection import Collection


class State(enum.Enum):
    COLLECTING = "collecting"  # automatic collection (device has no calibration)
    SESSION = "session"  # an operator's calibration session
    CALIBRATED = "calibrated"  # a calibration is in force, nothing collected
    IDLE = "idle"  # no calibration, automatic calibration off


def state_of(collection: Collection | None, calibrated: bool) -> State:
    """A device's state from its collection (None: nothing collects for it) and whether a record is in force."""
    if collection is not None:
        return State.SESSION if collection.session else State.COLLECTING
    return State.CALIBRATED if calibrated else State.IDLE


@dataclasses.dataclass(frozen=True)
class IntakeFigures:
    """What the raw intake in front of the calibrator saw (``services.calibrator.intake``), set by the service loop."""

    raw_messages: int = 0  # raw messages that arrived (= received_batches + raw:* drops once the queue is empty)
    queued: int = 0  # raw messages waiting now
    queue_high_water: int = 0  # most raw messages ever waiting at once
    enrolled: int = 0  # new device ids taken on (at most --enrol-rate a second)


@dataclasses.dataclass(frozen=True)
class Counters:
    """What the calibrator did since it started, each figure from the part that counts it."""

    received_batches: int = 0  # collection
    received_samples: int = 0  # collection
    fits: int = 0  # fitting
    accepted: int = 0  # fitting
    rejected: int = 0  # fitting
    stored: int = 0  # records
    evicted_devices: int = 0  # collections dropped for --max-devices
    no_gyroscope: int = 0  # raw batches without the gyroscope their collection's method (gyro-ellipsoid) needs
    refresh_fits: int = 0  # in-service refreshes fitted (``magnet.calibrator.refresh``)
    refreshed: int = 0  # ... committed as new versions (--recalibrate auto)
    proposed: int = 0  # ... opened as sessions for a person to commit (--recalibrate propose)
    forgotten_devices: int = 0  # roster entries (last seen, reported place, open alerts) dropped for --max-devices
    takeovers: int = 0  # times it became the active calibrator of its shard after standing by
    unverified_records: int = 0  # records in force its signing key does not verify (served as stored, unsigned)
    sensor_changes: int = 0  # devices whose batches came from another sensor than before (hardware ids)
    sensors_back: int = 0  # ... whose sensor's own record was put back in force from the history
    raw_messages: int = 0  # the intake's figures (IntakeFigures)
    queued: int = 0
    queue_high_water: int = 0
    enrolled: int = 0


@dataclasses.dataclass(frozen=True)
class CalibratorStatus:
    """The answer of ``<prefix>/@status/<name>``: counters, devices per state, drops by cause."""

    name: str
    counters: Counters
    devices: dict[str, int]
    dropped: dict[str, int]
    shard: str = "0/1"
    lease: str = "active"  # or "standby": another calibrator of the shard holds the lease (services.calibrator.lease)
    store_problem: str | None = None  # why the store takes no record (its file deleted or replaced), None while it does

    def to_dict(self) -> dict[str, Any]:
        return {
            "v": wire.RECORD_VERSION,
            "service": "calibrator",
            "name": self.name,
            **dataclasses.asdict(self.counters),
            "devices": dict(self.devices),
            "dropped": dict(self.dropped),
            "dropped_total": sum(self.dropped.values()),
            "shard": self.shard,
            "lease": self.lease,
            "store": "ok" if self.store_problem is None else "gone",
            "store_problem": self.store_problem,
        }


def devices_by_state(states: list[State]) -> dict[str, int]:
    """How many devices are in each state (every state named, 0 included)."""
    return {s.value: states.count(s) for s in State}
