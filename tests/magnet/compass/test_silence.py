"""A device the compass has not heard of for ``SILENT_S`` has its filter forgotten (``magnet.compass.silence``): a
flood of new ids, then silence, leaves the filters of the devices that still send, and those go on unrestarted."""

from __future__ import annotations

import numpy as np
import pytest
from compass_steps import NOW_NS, compass_core, heading_batches

from magnet import wire
from magnet.compass.silence import SILENT_S, Silence
from magnet.earth.expected import Earth

PERIOD_NS = 10_000_000
SECOND_NS = 1_000_000_000


def _batch(device: str, seq: int, n: int = 10) -> wire.RawBatch:
    """Batch ``seq`` of a level device turning at 0.2 rad/s with a gyroscope (so it gets a filter), 100 Hz."""
    t_ns = 10**12 + (seq * n + np.arange(n, dtype=np.int64)) * PERIOD_NS
    yaw = 0.2 * (t_ns - 10**12) / 1e9
    mag = np.c_[20 * np.cos(yaw), -20 * np.sin(yaw), np.full(n, 40.0)]
    acc = np.tile([0.0, 0.0, 9.81], (n, 1))
    gyr = np.tile([0.0, 0.0, 0.2], (n, 1))
    return wire.RawBatch(device, seq, "sim", t_ns, mag, acc, None, gyr)


def test_a_flood_of_new_ids_then_silence_leaves_the_filters_of_the_devices_that_send():
    compass = compass_core(Earth(declination_deg=0.0))
    heading_batches(compass, [_batch("steady", 0)], NOW_NS)
    baseline = set(compass.filters.devices)
    for k in range(5):  # a flood: 200 new ids, one batch each, over 5 s
        heading_batches(compass, [_batch(f"flood-{k}-{i}", 0) for i in range(40)], NOW_NS + k * SECOND_NS)
    heading_batches(compass, [_batch("steady", 1)], NOW_NS + 5 * SECOND_NS)
    assert len(compass.filters.devices) == 201
    later_ns = NOW_NS + int((SILENT_S + 5) * SECOND_NS)
    heading_batches(compass, [_batch("steady", 2)], later_ns)
    assert set(compass.filters.devices) == baseline == {"steady"}
    assert compass.silence.forgotten == 200 and len(compass.silence.heard_ns) == 1
    assert compass.filters.devices["steady"].restarts == 1  # the start only: a device that sends keeps its filter


def test_a_device_back_after_a_silence_starts_a_filter_again():
    compass = compass_core(Earth(declination_deg=0.0))
    heading_batches(compass, [_batch("phone", 0)], NOW_NS)
    heading_batches(compass, [_batch("other", 0)], NOW_NS + int(SILENT_S * SECOND_NS))
    assert "phone" not in compass.filters.devices
    out = heading_batches(compass, [_batch("phone", 1)], NOW_NS + int(SILENT_S * SECOND_NS))
    assert np.isfinite(out[0].heading_deg).all() and compass.filters.devices["phone"].restarts == 1


def test_silence_gives_each_silent_device_once_least_recently_heard_first():
    silence = Silence(max_devices=3, silent_s=10.0)
    assert silence.heard(["a", "b"], 0) == []
    assert silence.heard(["c", "a"], 5 * SECOND_NS) == []
    assert silence.heard([], 10 * SECOND_NS) == ["b"]
    assert silence.heard(["d"], 15 * SECOND_NS) == ["c", "a"]
    assert silence.heard([], 15 * SECOND_NS) == [] and list(silence.heard_ns) == ["d"]
    assert silence.forgotten == 3
    silence.heard(["e", "f", "g", "h"], 16 * SECOND_NS)  # bounded as every per-device table
    assert len(silence.heard_ns) == 3


def test_a_clock_that_goes_back_forgets_nobody():
    silence = Silence(max_devices=10, silent_s=10.0)
    silence.heard(["a"], 100 * SECOND_NS)
    assert silence.heard(["b"], 50 * SECOND_NS) == []


@pytest.mark.parametrize("silent_s", [0.0, -1.0, float("nan")])
def test_a_silence_must_be_positive(silent_s):
    with pytest.raises(ValueError, match="must be > 0 s"):
        Silence(10, silent_s)
