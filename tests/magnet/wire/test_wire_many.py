"""The batch decoder and encoder of the compass's hot path agree with the one-message ones, verdict for verdict."""

import msgpack
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from magnet import wire


def _raw(device: str, n: int = 3, acc: bool = True, seq: int = 1, gyr: bool = False) -> wire.RawBatch:
    rng = np.random.default_rng(len(device) + n)
    return wire.RawBatch(
        device,
        seq,
        "sim",
        np.arange(n, dtype=np.int64) + 10**18,
        rng.normal(0, 30, (n, 3)),
        rng.normal(0, 5, (n, 3)) if acc else None,
        gyr_rads=rng.normal(0, 1, (n, 3)) if gyr else None,
    )


GARBAGE = [
    b"junk",
    msgpack.packb([1, 2, 3]),
    msgpack.packb({"v": 3, "device": "a", "t_ns": [1], "mag_ut": [[1, 2, 3]]}),
    msgpack.packb({"v": 2, "device": "a", "t_ns": [1], "mag_ut": [[1, 2, 3]]}),
    msgpack.packb({"v": 1, "device": "a/b", "seq": 1, "t_ns": [1], "mag_ut": [[1, 2, 3]]}),
    msgpack.packb({"v": 1, "device": "n", "seq": 1, "t_ns": [1, 2], "mag_ut": [[1, 2, float("nan")], [1, 2, 3]]}),
    msgpack.packb({"v": 1, "device": "r", "seq": 1, "t_ns": [1, 2], "mag_ut": [[1, 2], [1, 2, 3]]}),
    msgpack.packb({"v": 1, "device": "m", "seq": 1, "t_ns": [1], "mag_ut": [[1e9, 0, 0]]}),
    msgpack.packb({"v": 1, "device": "g", "seq": 1, "t_ns": [1], "mag_ut": [[1, 2, 3]], "acc_ms2": [[1e6, 0, 0]]}),
    msgpack.packb({"v": 1, "device": "t", "seq": 1, "t_ns": [1.5], "mag_ut": [[1, 2, 3]]}),
    msgpack.packb({"v": 1, "device": "e", "seq": 1, "t_ns": [], "mag_ut": []}),
    msgpack.packb({"v": 1, "device": "q", "t_ns": [1, 2], "mag_ut": [[1, 2, 3], [4, 5, 6]]}),  # no seq: valid
    msgpack.packb({"v": 1, "device": "y", "t_ns": [1], "mag_ut": [[1, 2, 3]], "gyr_rads": [[0.1, 0, 500]]}),
    msgpack.packb({"v": 1, "device": "z", "t_ns": [1], "mag_ut": [[1, 2, 3]], "gyr_rads": [[0.1, float("inf"), 0]]}),
    msgpack.packb({"v": 1, "device": "w", "t_ns": [1], "mag_ut": [[1, 2, 3]], "gyr_rads": [[0.1, 0]]}),
    msgpack.packb({"v": 1, "device": "x", "t_ns": [1, 2], "mag_ut": [[1, 2, 3]] * 2, "gyr_rads": [[0, 0, 0]]}),
    msgpack.packb({"v": 1, "device": "u", "t_ns": [1], "mag_ut": [[1, 2, 3]], "gyr_rads": [[0, 0, "a"]]}),
    msgpack.packb({"v": 1, "device": "o", "t_ns": [1], "mag_ut": [[1, 2, 3]], "gyr_rads": [[0.5, -0.5, 1]]}),
]


def _one_by_one(payloads):
    good, bad = [], []
    for index, payload in enumerate(payloads):
        try:
            good.append(wire.decode_raw(payload, with_truth=False))
        except wire.WireError as exc:
            bad.append((index, exc.cause))
    return good, bad


@settings(max_examples=40, deadline=None)
@given(
    st.lists(
        st.one_of(
            st.sampled_from(GARBAGE),
            st.tuples(
                st.sampled_from("abcd"), st.integers(1, 5), st.booleans(), st.booleans(), st.sampled_from([1, 2])
            ),
        ),
        max_size=12,
    )
)
def test_decode_raw_many_gives_the_verdicts_and_order_of_decode_raw(items):
    """v 1 and v 2 messages and garbage mixed in one drain: the same verdicts, order and numbers as one by one."""
    payloads = [
        item
        if isinstance(item, bytes)
        else wire.encode_raw(_raw(item[0], item[1], item[2], gyr=item[3]), version=item[4])
        for item in items
    ]
    columns, errors = wire.decode_raw_many(payloads)
    good, bad = _one_by_one(payloads)
    assert [(i, e.cause) for i, e in errors] == bad
    assert columns.devices == [b.device for b in good]
    assert columns.counts.tolist() == [len(b) for b in good]
    if good:
        np.testing.assert_array_equal(columns.mag_ut, np.concatenate([b.mag_ut for b in good]))
        np.testing.assert_array_equal(columns.t_ns, np.concatenate([b.t_ns for b in good]))
        for batch, again in zip(good, columns.batches()):
            assert (batch.acc_ms2 is None) == (again.acc_ms2 is None)
            assert (batch.gyr_rads is None) == (again.gyr_rads is None)
            if batch.gyr_rads is not None:
                np.testing.assert_array_equal(again.gyr_rads, batch.gyr_rads)


def test_columns_carry_gyro_with_nan_rows_where_absent():
    payloads = [wire.encode_raw(_raw("a", 2, gyr=True)), wire.encode_raw(_raw("b", 3)), b"junk"]
    columns, errors = wire.decode_raw_many(payloads)
    assert [i for i, _ in errors] == [2] and columns.gyr_rads.shape == (5, 3)
    assert np.isfinite(columns.gyr_rads[:2]).all() and np.isnan(columns.gyr_rads[2:]).all()
    assert [b.sensor for b in columns.batches()] == ["sim", "sim"]


def test_encode_headings_matches_encode_heading_byte_for_byte():
    batches = [_raw("a", 3), _raw("b", 1, acc=False), _raw("c", 4)]
    columns = wire.RawColumns.from_batches(batches)
    s = int(columns.counts.sum())
    arrays = [
        np.linspace(0, 359, s),
        np.linspace(5, 4, s),
        np.zeros(s),
        np.ones(s),
        np.arange(3.0 * s).reshape(s, 3),
        np.arange(s),
    ]
    quat = np.tile([1.0, 0, 0, 0], (s, 1))
    quat[3] = np.nan  # batch "b" has no attitude
    payloads = wire.encode_headings(columns, *arrays, 7.5, ["id-a", "", "id-c"], quat_wxyz=quat)
    bounds = np.concatenate([[0], np.cumsum(columns.counts)])
    for i, batch in enumerate(batches):
        lo, hi = bounds[i], bounds[i + 1]
        one = wire.HeadingBatch(
            batch.device,
            batch.seq,
            batch.t_ns,
            *(a[lo:hi] for a in arrays[:5]),
            7.5,
            ["id-a", "", "id-c"][i],
            arrays[5][lo:hi],
            None if i == 1 else quat[lo:hi],
        )
        assert payloads[i] == wire.encode_heading(one)
    assert wire.decode_heading(payloads[1]).quat_wxyz is None
    np.testing.assert_array_equal(wire.decode_heading(payloads[2]).quat_wxyz, quat[4:8])


@pytest.mark.parametrize("rows", [1, 3, 40, 3000])  # bin 8, bin 16 and bin 32 headers
def test_v2_heading_bytes_are_msgpacks_own(rows):
    """The v 2 encoder joins its messages from pieces: they must be exactly what msgpack makes of the same map."""
    batches = [_raw("a", rows), _raw("b", rows, acc=False)]
    columns = wire.RawColumns.from_batches(batches)
    s = int(columns.counts.sum())
    angles = [np.linspace(0, 359.99999, s), np.linspace(5, 4, s), np.zeros(s), np.ones(s)]
    quat = np.tile([1.0, 0, 0, 0], (s, 1))
    quat[rows] = np.nan  # batch "b" has no attitude
    payloads = wire.encode_headings(
        columns, *angles, np.arange(3.0 * s).reshape(s, 3), np.arange(s) % 32, [7.5, -2.25], ["id-a", ""], quat
    )
    for payload in payloads:
        assert msgpack.packb(msgpack.unpackb(payload), use_bin_type=True) == payload
    assert wire.decode_heading(payloads[0]).quat_wxyz is not None and wire.decode_heading(payloads[1]).quat_wxyz is None
