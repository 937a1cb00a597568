"""The drift trackers of many devices, fed batch by batch."""

from __future__ import annotations

import numpy as np

from magnet.bounded import Recent
from magnet.drift.alerts import Alert
from magnet.drift.settings import DEFAULT_DRIFT, DriftSettings, Reference
from magnet.drift.tracker import DriftTracker


class DriftMonitor:
    """The drift trackers of many devices: one per device with a calibration in force, for at most ``max_devices``
    devices (the least recently calibrated forgotten first, counted in ``trackers.evicted``)."""

    def __init__(self, settings: DriftSettings = DEFAULT_DRIFT, max_devices: int = 10_000) -> None:
        self.settings = settings
        self.trackers: Recent[str, DriftTracker] = Recent(max_devices)

    def calibration(self, device: str, reference: Reference, now_ns: int) -> list[Alert]:
        """A calibration came into force for ``device``: clear its open alerts and start afresh."""
        old = self.trackers.get(device)
        if old is not None and old.reference.calibration_id == reference.calibration_id:
            self.trackers.touch(device)
            old.set_model(reference.model_total_ut, reference.model_dip_deg)
            return []
        events = [] if old is None else old.clear_all(now_ns, f"calibration {reference.calibration_id} in force")
        self.trackers[device] = DriftTracker(device, reference, self.settings)
        return events

    def add(self, device: str, t_ns: np.ndarray, strength_ut: np.ndarray, dip_deg: np.ndarray) -> list[Alert]:
        tracker = self.trackers.get(device)
        return [] if tracker is None else tracker.add(t_ns, strength_ut, dip_deg)

    def add_columns(
        self, devices: list[str], bounds: list[int], t_ns: np.ndarray, strength_ut: np.ndarray, dip_deg: np.ndarray
    ) -> list[Alert]:
        """``add`` for B batches at once: devices (B,), bounds (B + 1) sample offsets, t_ns, strength_ut, dip_deg
        (S,). The window of every sample is computed once; a batch inside its device's current window is appended
        without further numpy work."""
        if not devices:
            return []
        index = t_ns // self.settings.window_ns
        starts, ends = np.asarray(bounds[:-1]), np.asarray(bounds[1:]) - 1
        first, last, last_ns = index[starts].tolist(), index[ends].tolist(), t_ns[ends].tolist()
        events: list[Alert] = []
        for i, device in enumerate(devices):
            tracker = self.trackers.get(device)
            if tracker is None:
                continue
            lo, hi = bounds[i], bounds[i + 1]
            if first[i] != last[i] or not tracker.add_within(first[i], last_ns[i], strength_ut[lo:hi], dip_deg[lo:hi]):
                events += tracker.add(t_ns[lo:hi], strength_ut[lo:hi], dip_deg[lo:hi])
        return events

    def silent(self, device: str) -> list[Alert]:
        """``device`` fell silent: its tracker's open window judged now (``DriftTracker.close_window``)."""
        tracker = self.trackers.get(device)
        return [] if tracker is None else tracker.close_window()

    def open_alerts(self) -> list[Alert]:
        return [alert for tracker in self.trackers.values() for alert in tracker.open_alerts]
