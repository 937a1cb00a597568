"""The collection part of the calibrator: one sample buffer per device (``magnet.calibration.collection.Collection``,
samples kept evenly spread over the sphere, at most ``--max-samples``), for at most ``--max-devices`` devices at once
(beyond, a newcomer's collection goes first: ``PROMOTE_AFTER_BATCHES``).
For a method that needs the gyroscope (gyro-ellipsoid), and for auto once a batch carries one, each raw batch's
``gyr_rads``, ``t_ns`` and ``seq`` go to the collection too (its ring of recent consecutive samples); a batch without a
gyroscope for gyro-ellipsoid is counted (``no_gyroscope``, in the status) and said in the device's progress (auto then
fits the ellipsoid on the cells).

A device with no calibration in force gets an automatic collection when automatic calibration is on; an operator's
session opens one of its own (``magnet.calibrator.sessions``), which the ``--max-devices`` bound never drops. A due
automatic collection is fitted only once its coverage reached ``--min-coverage`` (``ready``); until then the reason
is kept on the collection and goes out with its progress. The bounded queue and the enrolment rate in front of it
are ``services.calibrator.intake``. No zenoh, no store inside.
"""

from __future__ import annotations

import logging
from collections.abc import Iterator

from magnet import wire
from magnet.bounded import Graded
from magnet.calibration.collection import Collection
from magnet.calibrator.settings import Settings

log = logging.getLogger("magnet.calibrator")

#: a device's collection is on probation until this many raw batches came for it: beyond ``--max-devices`` the
#: collections on probation are evicted first (a flood of ids of a message or two each churns among itself; a real
#: device, sending batches again and again, keeps its collection; ``magnet.bounded.Graded``)
PROMOTE_AFTER_BATCHES = 5


class Collections:
    """The collections in progress, by device; counts the raw batches and samples received for them."""

    def __init__(self, settings: Settings) -> None:
        self.settings = settings
        self.by_device: Graded[str, Collection] = Graded(
            settings.max_devices, PROMOTE_AFTER_BATCHES, keep=lambda c: c.session
        )
        self.received_batches = 0
        self.received_samples = 0
        self.no_gyroscope = 0  # batches without the gyroscope for a collection whose method needs one
        self._warned = False

    def __contains__(self, device: object) -> bool:
        return device in self.by_device

    def __len__(self) -> int:
        return len(self.by_device)

    def __iter__(self) -> Iterator[str]:
        return iter(self.by_device)

    def get(self, device: str) -> Collection | None:
        return self.by_device.get(device)

    @property
    def evicted(self) -> int:
        """Collections dropped for the --max-devices bound."""
        return self.by_device.evicted

    def in_session(self, device: str) -> bool:
        collection = self.by_device.get(device)
        return collection is not None and collection.session

    def receive(self, batch: wire.RawBatch, calibrated: bool) -> Collection | None:
        """Count ``batch`` and add its samples to its device's collection: one is opened when the device has no
        calibration in force (``calibrated`` False) and automatic calibration is on. The collection, or None when
        nothing collects for the device."""
        self.received_batches += 1
        self.received_samples += len(batch)
        device = batch.device
        collection = self.by_device.get(device)
        if collection is None:
            if calibrated or not self.settings.auto:
                return None
            collection = self.by_device[device] = Collection(self.settings.method, False, self.settings.max_samples)
            self._say_evicted()
        self.by_device.touch(device)
        if collection.runs is not None and not collection.auto and batch.gyr_rads is None:
            self.no_gyroscope += 1
        collection.add(batch.mag_ut, batch.acc_ms2, batch.gyr_rads, batch.t_ns, batch.seq, batch.vel_ned_ms)
        return collection

    def ready(self, collection: Collection, now: float) -> bool:
        """Whether a fit may be tried on a due collection: a session's always; an automatic one once its coverage
        reached --min-coverage, or for a method that needs the gyroscope once its longest run turned about two axes
        (``Collection.turn_wait``); auto with a gyroscope: either. Else the reason is kept on it, and it waits for
        more samples."""
        if collection.session:
            return True
        waits = []
        if collection.runs is not None:
            waits.append(collection.turn_wait(self.settings.min_samples))
        if collection.runs is None or collection.auto:  # auto: the run turned enough, or the cells are covered
            cov = collection.coverage()
            waits.append(
                f"coverage {cov.fraction:.0%} below {self.settings.min_coverage:.0%}: "
                f"{', '.join(cov.missing) or 'move through more attitudes'}"
                if cov.fraction < self.settings.min_coverage
                else ""
            )
        wait = "" if not all(waits) else "; or ".join(waits)
        if wait:
            collection.postpone(now, wait)
        return not wait

    def open_session(self, device: str, method: str) -> None:
        """A fresh collection for an operator's session with ``method`` (a checked method name)."""
        self.by_device[device] = Collection(method, True, self.settings.max_samples)
        self._say_evicted()

    def propose(self, device: str, collection: Collection) -> None:
        """An in-service refresh that passed: its collection becomes a session holding the fit, for a person to
        commit (``--recalibrate propose``)."""
        collection.session = True
        self.by_device[device] = collection
        self._say_evicted()

    def end(self, device: str) -> None:
        """Collection for ``device`` is over (stored, or its session aborted)."""
        self.by_device.pop(device, None)

    def clear(self) -> list[str]:
        """Drop every collection; the devices whose session was dropped with it, sorted."""
        sessions = sorted(d for d, c in self.by_device.items() if c.session)
        self.by_device.clear()
        return sessions

    def _say_evicted(self) -> None:
        if self.by_device.evicted and not self._warned:
            self._warned = True
            log.warning(
                "more than %d devices collecting at once: the least recently seen are dropped (counted in status "
                "evicted_devices; raise --max-devices if they are genuine)",
                self.settings.max_devices,
            )
