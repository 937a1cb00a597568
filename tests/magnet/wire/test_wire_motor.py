"""The optional per-sample scalars of raw messages (current_a, throttle): carried, checked, refused when wrong."""

from __future__ import annotations

import msgpack
import numpy as np
import pytest

from magnet import wire
from magnet.wire.arrays import bin_array


def _batch(n: int = 4, **extra: np.ndarray) -> wire.RawBatch:
    return wire.RawBatch("d", 1, "s", np.arange(n, dtype=np.int64), np.full((n, 3), 20.0), **extra)


@pytest.mark.parametrize("version", wire.VERSIONS)
def test_current_and_throttle_round_trip(version: int) -> None:
    current, throttle = np.array([0.0, 12.5, 40.0, -2.0]), np.array([0.0, 0.25, 1.0, 0.5])
    batch = wire.decode_raw(wire.encode_raw(_batch(current_a=current, throttle=throttle), version))
    assert batch.current_a is not None and batch.throttle is not None
    np.testing.assert_allclose(batch.current_a, current)
    np.testing.assert_allclose(batch.throttle, throttle)


def test_nan_means_unknown_at_that_sample() -> None:
    current = np.array([np.nan, 2.0, np.nan, 4.0])
    batch = wire.decode_raw(wire.encode_raw(_batch(current_a=current)))
    assert batch.current_a is not None
    np.testing.assert_array_equal(batch.current_a, current)


def test_columns_hold_nan_where_a_batch_carries_none() -> None:
    payloads = [wire.encode_raw(_batch(2, current_a=np.array([1.0, 2.0]))), wire.encode_raw(_batch(3))]
    columns, errors = wire.decode_raw_many(payloads)
    assert not errors
    np.testing.assert_array_equal(columns.current[:2], [1.0, 2.0])
    assert np.isnan(columns.current[2:]).all() and np.isnan(columns.thr).all()
    first, second = columns.batches()
    assert first.current_a is not None and second.current_a is None and first.throttle is None
    kept = columns.select(np.array([False, True]))
    assert kept.current.shape == (3,) and np.isnan(kept.current).all()


def _message(version: int, **fields: object) -> bytes:
    message = msgpack.unpackb(wire.encode_raw(_batch(), version), raw=False)
    message.update(fields)
    return msgpack.packb(message, use_bin_type=True)


@pytest.mark.parametrize(
    ("fields", "cause"),
    [
        ({"current_a": [1.0, 2.0, 3.0]}, "bad-shape"),  # one short
        ({"current_a": [True, False, True, True]}, "bad-shape"),  # booleans are not amps
        ({"current_a": [1.0, "x", 3.0, 4.0]}, "bad-shape"),
        ({"current_a": 3.0}, "bad-shape"),
        ({"current_a": [1.0, float("inf"), 3.0, 4.0]}, "non-finite"),
        ({"current_a": [1.0, 1e6, 3.0, 4.0]}, "absurd-magnitude"),
        ({"throttle": [0.0, 0.5, 1.5, 0.0]}, "absurd-magnitude"),
        ({"throttle": [0.0, -0.1, 0.5, 0.0]}, "absurd-magnitude"),
    ],
)
def test_bad_scalars_are_refused_with_their_cause(fields: dict[str, object], cause: str) -> None:
    with pytest.raises(wire.WireError) as info:
        wire.decode_raw(_message(1, **fields))
    assert info.value.cause == cause


def test_binary_scalars_checked_for_dtype_length_and_values() -> None:
    with pytest.raises(wire.WireError):  # a boolean array is no float dtype
        wire.decode_raw(_message(2, throttle=bin_array([True, False, True, True], "|b1")))
    with pytest.raises(wire.WireError):
        wire.decode_raw(_message(2, throttle=bin_array([0.1, 0.2], "<f4")))
    with pytest.raises(wire.WireError) as info:
        wire.decode_raw(_message(2, current_a=bin_array([1.0, np.inf, 0.0, 0.0], "<f4")))
    assert info.value.cause == "non-finite"
    columns, errors = wire.decode_raw_many([_message(2, throttle=bin_array([2.0] * 4, "<f4")), _message(2)])
    assert [e.cause for _, e in errors] == ["absurd-magnitude"] and len(columns.devices) == 1
