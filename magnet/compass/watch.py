"""The compass's watch over its devices: each device's place and Earth (``magnet.fleet.places.Places``) and its
drift (``magnet.drift.DriftMonitor``); the alerts to publish on ``<prefix>/<device>/alert``. Pure."""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from magnet import wire
from magnet.drift.settings import DEFAULT_DRIFT, DriftSettings, Reference
from magnet.earth.expected import Earth
from magnet.earth.geomag import DateLike
from magnet.earth.location import Location
from magnet.fleet.places import Places
from magnet.units import ut_per_unit

if TYPE_CHECKING:
    from magnet.drift.alerts import Alert
    from magnet.drift.monitor import DriftMonitor

#: alert events waiting to be published at most (the oldest dropped beyond: the open ones are also queryable)
MAX_PENDING_ALERTS = 10_000
#: devices with a drift tracker at most, by default
MAX_TRACKED = 10_000


class DeviceWatch:
    """Places and drift of the devices a compass serves: reported places (bounded by the ``Places``) and drift
    trackers for at most ``max_devices`` devices (the least recently calibrated forgotten first, counted in
    ``evicted``)."""

    def __init__(
        self, places: Places, drift: DriftSettings | None = DEFAULT_DRIFT, max_devices: int = MAX_TRACKED
    ) -> None:
        self.places = places
        self.monitor: DriftMonitor | None = None
        if drift is not None:  # the trackers' module only where drift is watched (not in ``magnet heading``)
            from magnet.drift.monitor import DriftMonitor

            self.monitor = DriftMonitor(drift, max_devices)
        self.pending: list[Alert] = []
        self.max_devices = max_devices
        self.date: DateLike = None  # the day of the last step (the model's date where no --date is given)

    @property
    def evicted(self) -> int:
        """Reported places and drift trackers forgotten for the bounds."""
        return self.places.reported.evicted + (0 if self.monitor is None else self.monitor.trackers.evicted)

    def earths(self, devices: list[str], locations: list[Location | None] | None, date: DateLike) -> list[Earth]:
        """The Earth of each batch's device on ``date``, taking the locations the batches report."""
        self.date = date
        if locations is not None:
            for device, location in zip(devices, locations):
                if self.places.report(device, location):
                    self._moved(device)
        return [self.places.earth(device, date) for device in devices]

    def _moved(self, device: str) -> None:
        tracker = None if self.monitor is None else self.monitor.trackers.get(device)
        if tracker is not None:
            earth = self.places.earth(device, self.date)
            tracker.set_model(earth.total_ut, earth.inclination_deg)

    def calibration(self, record: wire.DeviceCalibration, now_ns: int) -> None:
        """A calibration came into force: drift is judged against it from now on (open alerts clear)."""
        if self.monitor is None:
            return
        cal, earth = record.calibration, self.places.earth(record.device, self.date)
        in_ut = ut_per_unit(cal.output_unit) == 1.0
        reference = Reference(
            cal.field_strength or None,
            float(cal.quality.residual_rms_ut or 0.0),
            earth.total_ut if in_ut else None,
            earth.inclination_deg,
            record.created_ns,
            record.id,
        )
        self._queue(self.monitor.calibration(record.device, reference, now_ns))

    def observe(
        self, devices: list[str], bounds: list[int], t_ns: np.ndarray, strength_ut: np.ndarray, dip_deg: np.ndarray
    ) -> None:
        """Feed the samples of each batch (t_ns, strength_ut, dip_deg (S,)) to its device's tracker (devices with a
        calibration in force have one)."""
        if self.monitor is None:
            return
        self._queue(self.monitor.add_columns(devices, bounds, t_ns, strength_ut, dip_deg))

    def tracks(self, device: str) -> bool:
        """Whether ``device`` has a drift tracker."""
        return self.monitor is not None and device in self.monitor.trackers

    def silent(self, device: str) -> None:
        """``device`` fell silent (``magnet.compass.silence``): its drift window judged now, not kept."""
        if self.monitor is not None:
            self._queue(self.monitor.silent(device))

    def _queue(self, alerts: list[Alert]) -> None:
        self.pending += alerts
        if len(self.pending) > MAX_PENDING_ALERTS:
            del self.pending[:-MAX_PENDING_ALERTS]

    def take(self) -> list[Alert]:
        """The alert events to publish, oldest first (and forget them)."""
        out, self.pending = self.pending, []
        return out

    def open_alerts(self) -> list[Alert]:
        return [] if self.monitor is None else self.monitor.open_alerts()
