"""A drift tracker's open window holds its own samples, not the drains they came in (docs/front-door.md, "Memory per
service"): the compass hands each batch as a slice of its whole drain's |B| and dip arrays, and a view kept the whole
drain alive until the window closed, and for good in the last window of a device that stopped sending."""

from __future__ import annotations

import numpy as np

from magnet.drift import NS_PER_S, DriftMonitor, Reference

DRAIN = 16_000  # samples of a drain of a flood of ids (8,000 messages of 2 samples)
BATCH = 10


def _window_bytes(monitor: DriftMonitor, device: str) -> int:
    """Bytes the device's open window keeps alive: each array's own data, or the whole array it views."""
    window = monitor.trackers[device].window
    assert window is not None
    return sum((a.base if a.base is not None else a).nbytes for a in [*window.strength, *window.dip])


def test_a_stopped_devices_last_window_keeps_only_its_samples():
    monitor = DriftMonitor()
    monitor.calibration("phone", Reference(50.0, 0.5, calibration_id="c1"), 0)
    for k in range(150):  # 150 drains within one 30 s window, the device's batch at the start of each
        t_ns = np.full(DRAIN, k * NS_PER_S // 10, dtype=np.int64)
        strength, dip = np.full(DRAIN, 50.0), np.full(DRAIN, 67.0)
        monitor.add_columns(["phone", "flood"], [0, BATCH, DRAIN], t_ns, strength, dip)
    assert monitor.trackers["phone"].window.count == 150 * BATCH
    # before: 150 drains x 2 arrays x 128 kB = 38 MB kept by 1,500 samples
    assert _window_bytes(monitor, "phone") <= 2 * 150 * BATCH * 8


def test_a_decimated_window_copies_too():
    monitor = DriftMonitor()
    monitor.calibration("phone", Reference(50.0, 0.5, calibration_id="c1"), 0)
    big = np.full(DRAIN, 50.0)
    for k in range(3):  # 3 x 16,000 samples in one window: past the cap of 4,096, decimated
        t_ns = np.full(DRAIN, k, dtype=np.int64)
        monitor.add_columns(["phone"], [0, DRAIN], t_ns, big, big)
    window = monitor.trackers["phone"].window
    assert window.stride > 1 and _window_bytes(monitor, "phone") <= 4 * window.cap * 8
