"""What the calibrator reports: the state of a device, its counters and the answer of ``<prefix>/@status/<name>``."""

from __future__ import annotations

import dataclasses
import enum
from typing import Any

from magnet import wire


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
    forgotten_devices: int = 0  # fleet-book entries (last seen, reported place, open alerts) dropped for --max-devices
    takeovers: int = 0  # times it became the active calibrator of its shard after standing by
    unverified_records: int = 0  # records in force its signing key does not verify (served as stored, unsigned)
    raw_messages: int = 0  # raw messages that arrived (= received_batches + raw:* drops once the queue is empty)
    queued: int = 0  # raw messages waiting now (services.calibrator.intake)
    queue_high_water: int = 0  # most raw messages ever waiting at once
    enrolled: int = 0  # new device ids taken on (at most --enrol-rate a second)


@dataclasses.dataclass(frozen=True)
class CalibratorStatus:
    """The answer of ``<prefix>/@status/<name>``: counters, devices per state, drops by cause."""

    name: str
    counters: Counters
    devices: dict[str, int]
    dropped: dict[str, int]
    shard: str = "0/1"
    lease: str = "active"  # or "standby": another calibrator of the shard holds the lease (services.calibrator.lease)

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
        }
