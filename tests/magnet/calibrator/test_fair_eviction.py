"""Issue 32: a flood of new ids made the calibrator evict 6,135 devices: beyond ``--max-devices`` the least recently
seen collection went, so real devices that were quiet for a moment went before a flood's one-message ids. Now the
newcomers go first (``magnet.bounded.Graded``): a real device keeps its collection through any flood."""

from __future__ import annotations

import numpy as np
import pytest

from magnet import wire
from magnet.bounded import Graded
from magnet.calibrator.collecting import PROMOTE_AFTER_BATCHES, Collections
from services.calibrator.settings import CalibratorSettings


def batch(device: str) -> wire.RawBatch:
    mag = np.random.default_rng(len(device)).normal(size=(10, 3)) * 40
    return wire.RawBatch(device, 0, "sim", np.arange(10, dtype=np.int64), mag)


def test_a_flood_of_new_ids_evicts_itself_not_the_real_devices():
    collections = Collections(CalibratorSettings(max_devices=100))
    real = [f"real-{k}" for k in range(10)]
    for _ in range(PROMOTE_AFTER_BATCHES):
        for device in real:
            collections.receive(batch(device), calibrated=False)
    for k in range(1_000):  # then the real devices are quiet while 1,000 ids send one message each
        collections.receive(batch(f"flood-{k}"), calibrated=False)
    assert all(device in collections for device in real)
    assert len(collections) == 100 and collections.evicted == 1_000 - 90
    assert "flood-999" in collections  # the newest newcomers stay, within the bound


def test_graded_evicts_newcomers_first_then_the_least_recently_seen():
    graded: Graded[str, int] = Graded(3, promote_after=2)
    graded["a"], graded["b"] = 1, 2
    graded.touch("a")
    graded.touch("a")  # a promoted
    graded["c"] = 3
    graded["d"] = 4  # b and c on probation: b, the least recent of them, goes
    assert list(graded) == ["a", "c", "d"] and graded.evicted == 1
    for key in ("c", "d"):
        graded.touch(key)
        graded.touch(key)
    graded["e"] = 5  # every old key promoted: the least recently seen of all goes, never the newcomer
    assert list(graded) == ["c", "d", "e"] and graded.evicted == 2
    del graded["e"]
    graded.clear()
    assert len(graded) == 0
    with pytest.raises(ValueError, match="promote_after"):
        Graded(3, promote_after=0)
