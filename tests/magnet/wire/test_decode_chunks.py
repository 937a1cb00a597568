"""``decode_raw_many`` works through a drain ``DECODE_CHUNK`` messages at a time: the same columns and verdicts as
one pass, and a flood's drain never holds all its unpacked messages at once (docs/front-door.md, "Memory per
service")."""

import tracemalloc

import msgpack
import numpy as np
import pytest

from magnet import wire
from magnet.earth.location import Location
from magnet.wire import raw_decode


def _batch(i: int) -> wire.RawBatch:
    """Message ``i`` of a mixed drain: every few carry a location, a vehicle, a hardware id, a velocity, a current."""
    rng = np.random.default_rng(i)
    n = 1 + i % 4
    return wire.RawBatch(
        f"d{i % 7}",
        i,
        "sim",
        np.arange(n, dtype=np.int64) + 10**18,
        rng.normal(0, 30, (n, 3)),
        rng.normal(0, 5, (n, 3)) if i % 2 else None,
        gyr_rads=rng.normal(0, 1, (n, 3)) if i % 3 == 0 else None,
        location=Location(50.0 + i % 5, 30.0) if i % 5 == 0 else None,
        vel_ned_ms=rng.normal(0, 2, (n, 3)) if i % 4 == 1 else None,
        current_a=np.full(n, 1.5) if i % 6 == 2 else None,
        vehicle="car" if i % 5 == 3 else "",
        hardware_id=7 if i % 7 == 4 else 0,
    )


def _payloads() -> list[bytes]:
    garbage = [b"junk", msgpack.packb({"v": 1, "device": "m", "seq": 1, "t_ns": [1], "mag_ut": [[1e9, 0, 0]]})]
    return [garbage[i % 2] if i % 9 == 8 else wire.encode_raw(_batch(i), version=1 + i % 2) for i in range(40)]


def _same(a: np.ndarray | None, b: np.ndarray | None) -> None:
    assert (a is None) == (b is None)
    if a is not None:
        np.testing.assert_array_equal(a, b)


@pytest.mark.parametrize("chunk", [1, 3, 8, 39])
def test_chunks_give_the_columns_and_verdicts_of_one_pass(monkeypatch, chunk):
    payloads = _payloads()
    whole, whole_errors = wire.decode_raw_many(payloads)
    monkeypatch.setattr(raw_decode, "DECODE_CHUNK", chunk)
    parts, part_errors = wire.decode_raw_many(payloads)
    assert [(i, e.cause) for i, e in part_errors] == [(i, e.cause) for i, e in whole_errors]
    assert [i for i, _ in part_errors] == [i for i in range(40) if i % 9 == 8]
    for name in ("devices", "seqs", "sensors", "locations", "vehicles", "hardware_ids"):
        assert getattr(parts, name) == getattr(whole, name), name
    for name in ("counts", "t_ns", "mag_ut", "acc_ms2", "gyr_rads", "vel_ned_ms", "current_a", "throttle"):
        _same(getattr(parts, name), getattr(whole, name))
    assert parts.bounds == whole.bounds


def test_chunks_of_plain_batches_name_no_location_vehicle_or_hardware_id(monkeypatch):
    monkeypatch.setattr(raw_decode, "DECODE_CHUNK", 2)
    payloads = [wire.encode_raw(wire.RawBatch(f"p{i}", i, "sim", np.array([1, 2]), np.ones((2, 3)))) for i in range(5)]
    columns, errors = wire.decode_raw_many(payloads)
    assert errors == [] and columns.devices == [f"p{i}" for i in range(5)]
    assert columns.locations is None and columns.vehicles is None and columns.hardware_ids is None


def test_no_payloads_give_empty_columns():
    columns, errors = wire.decode_raw_many([])
    assert errors == [] and columns.devices == [] and columns.t_ns.shape == (0,)


def test_a_flood_drain_holds_one_chunk_of_unpacked_messages_at_a_time():
    """4,000 new ids of 2 samples each (the soak's flood): one pass held every unpacked message at once, 9 MB of
    Python objects beyond the columns it returned; a chunk at a time holds about 1 MB."""
    mag, t_ns = np.array([[20.0, 5.0, 40.0], [21.0, 5.0, 40.0]]), np.array([1, 2], dtype=np.int64)
    payloads = [wire.encode_raw(wire.RawBatch(f"flood-{i}", 0, "sim", t_ns, mag)) for i in range(4000)]
    tracemalloc.start()
    try:
        before = tracemalloc.get_traced_memory()[0]
        columns, errors = wire.decode_raw_many(payloads)
        held, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert errors == [] and len(columns.devices) == 4000
    transient_mb = (peak - held) / 2**20
    assert transient_mb < 3.0, f"{transient_mb:.1f} MB held at once beyond the columns ({(held - before) >> 10} kB)"
