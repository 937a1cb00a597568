"""The pipeline benchmark's load: its messages, stamped without encoding them again, are the edge's own bytes."""

import dataclasses

import numpy as np
import pytest

from magnet import wire
from services.bench.ceiling import _fleet_batches, _Stamper


@pytest.mark.parametrize("batch", [1, 10, 100])
def test_stamped_messages_are_the_edges_bytes(batch):
    raw = _fleet_batches(3, batch, True, 1)[0][2]
    stamper = _Stamper(raw)
    for seq in (0, 1, 127, 128, 70_000, 2**40):
        t_ns = 1_800_000_000_000_000_000 + np.arange(batch, dtype=np.int64) * 10_000_000 + seq
        expected = wire.encode_raw(dataclasses.replace(raw, seq=seq, t_ns=t_ns))
        assert stamper.stamp(seq, t_ns) == expected
    decoded = wire.decode_raw(stamper.stamp(5, t_ns))
    assert decoded.seq == 5 and np.array_equal(decoded.t_ns, t_ns)
