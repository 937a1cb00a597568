"""Wire v 2 (arrays as little-endian bytes with dtype and shape): every message kind round-trips in both versions, and
malformed v 2 arrays are refused with a countable cause by the same decoder as v 1 garbage."""

import json

import msgpack
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

from magnet import wire
from magnet.model import Calibration

VERSIONS = (1, 2)


def _as_sent(values, version):
    """What the receiver gets back: exact in v 1, rounded to single precision in v 2 (floats written as <f4)."""
    arr = np.asarray(values, dtype=float)
    return arr if version == 1 else arr.astype(np.float32).astype(float)


def _vectors(limit):
    return lambda n: hnp.arrays(np.float64, (n, 3), elements=st.floats(-limit, limit, allow_nan=False))


@st.composite
def raw_batches(draw):
    n = draw(st.integers(1, 40))
    optional = lambda strategy: draw(st.one_of(st.none(), strategy))  # noqa: E731
    t_ns = np.sort(draw(hnp.arrays(np.int64, n, elements=st.integers(0, 2**62))))  # time never runs backwards
    truth = optional(st.just({k: np.linspace(0, 359, n) for k in wire.TRUTH_FIELDS}))
    return wire.RawBatch(
        draw(st.sampled_from(["d", "imu-1", "ü-7"])),
        draw(st.integers(0, 2**40)),
        draw(st.sampled_from(["sim", "icm20948"])),
        t_ns,
        draw(_vectors(4999)(n)),
        optional(_vectors(1999)(n)),
        truth,
        optional(_vectors(99)(n)),
    )


@settings(max_examples=30, deadline=None)
@given(batch=raw_batches(), version=st.sampled_from(VERSIONS))
def test_raw_round_trips_in_both_versions(batch, version):
    payload = wire.encode_raw(batch, version=version)
    assert msgpack.unpackb(payload)["v"] == version
    back = wire.decode_raw(payload)
    assert (back.device, back.seq, back.sensor) == (batch.device, batch.seq, batch.sensor)
    assert back.t_ns.dtype == np.int64
    np.testing.assert_array_equal(back.t_ns, batch.t_ns)
    np.testing.assert_array_equal(back.mag_ut, _as_sent(batch.mag_ut, version))
    for name in ("acc_ms2", "gyr_rads"):
        sent, got = getattr(batch, name), getattr(back, name)
        assert (got is None) == (sent is None)
        if sent is not None:
            np.testing.assert_array_equal(got, _as_sent(sent, version))
    assert (back.truth is None) == (batch.truth is None)
    if batch.truth is not None:
        for name in wire.TRUTH_FIELDS:
            np.testing.assert_array_equal(back.truth[name], _as_sent(batch.truth[name], version))
    columns, errors = wire.decode_raw_many([payload])
    assert not errors and columns.devices == [batch.device]


@st.composite
def heading_batches(draw):
    n = draw(st.integers(1, 40))

    def angle(lo, hi):
        return draw(hnp.arrays(np.float64, n, elements=st.floats(lo, hi, exclude_max=True)))

    quat = None
    if draw(st.booleans()):
        raw = draw(hnp.arrays(np.float64, (n, 4), elements=st.floats(0.1, 1)))
        quat = raw / np.linalg.norm(raw, axis=1, keepdims=True)
    return wire.HeadingBatch(
        "dev",
        draw(st.integers(0, 1000)),
        np.arange(n, dtype=np.int64) + 10**18,
        angle(0, 360),
        angle(0, 360),
        angle(-90, 90),
        angle(-180, 180),
        draw(_vectors(200)(n)),
        draw(st.floats(-30, 30)),
        draw(st.sampled_from(["", "abc"])),
        draw(hnp.arrays(np.int64, n, elements=st.integers(0, 31))),
        quat,
    )


@settings(max_examples=30, deadline=None)
@given(batch=heading_batches(), version=st.sampled_from(VERSIONS))
def test_heading_round_trips_in_both_versions(batch, version):
    back = wire.decode_heading(wire.encode_heading(batch, version=version))
    assert (back.device, back.seq, back.calibration_id) == (batch.device, batch.seq, batch.calibration_id)
    assert back.declination_deg == batch.declination_deg
    np.testing.assert_array_equal(back.t_ns, batch.t_ns)
    np.testing.assert_array_equal(back.flags, batch.flags)
    for name in ("pitch_deg", "roll_deg", "field_ut"):
        np.testing.assert_array_equal(getattr(back, name), _as_sent(getattr(batch, name), version))
    for name in ("heading_deg", "true_heading_deg"):  # in [0, 360) after rounding too
        got = getattr(back, name)
        assert ((got >= 0) & (got < 360)).all()
        np.testing.assert_allclose(np.cos(np.radians(got - getattr(batch, name))), 1.0, atol=1e-9)
    assert (back.quat_wxyz is None) == (batch.quat_wxyz is None)
    if batch.quat_wxyz is not None:
        np.testing.assert_array_equal(back.quat_wxyz, _as_sent(batch.quat_wxyz, version))


@settings(max_examples=30, deadline=None)
@given(
    offset=hnp.arrays(np.float64, 3, elements=st.floats(-100, 100)),
    scale=st.floats(0.5, 2.0),
    version=st.sampled_from(VERSIONS),
    created=st.integers(0, 2**62),
)
def test_records_round_trip_and_are_read_with_either_version_number(offset, scale, version, created):
    """Calibration and progress records carry no sample arrays: the same map in both versions, both read."""
    cal = Calibration("ellipsoid", offset, np.diag([scale, 1.0, 1.0]), field_strength=50.0)
    record = {**wire.calibration_record("dev", cal, created), "v": version}
    back = wire.decode_calibration(msgpack.packb(record))
    assert back.id == cal.content_id and back.created_ns == created
    np.testing.assert_array_equal(back.calibration.offset, offset)
    progress = msgpack.unpackb(wire.encode_progress("dev", wire.Progress("collecting", created)))
    assert wire.decode_progress(msgpack.packb({**progress, "v": version}))["t_ns"] == created


# ------------------------------------------------------------------------------------------------ malformed v 2


def _v2(**changes):
    batch = wire.RawBatch("dev", 1, "sim", np.arange(5, dtype=np.int64), np.ones((5, 3)), np.ones((5, 3)))
    message = msgpack.unpackb(wire.encode_raw(batch))
    message.update(changes)
    return msgpack.packb({k: v for k, v in message.items() if v is not ...})


def _bin(dtype, shape, data=None):
    count = int(np.prod(shape))
    fill = np.ones(count, dtype=dtype if dtype[1:2] in "fiu" else "<f4").tobytes()
    return {"dtype": dtype, "shape": list(shape), "data": data if data is not None else fill}


def _f4(rows):
    return {"dtype": "<f4", "shape": [len(rows), 3], "data": np.array(rows, dtype="<f4").tobytes()}


MALFORMED_V2 = [
    (_v2(mag_ut=_bin("<f4", (5, 3), b"\x00" * 59)), "bad-shape"),  # wrong byte count
    (_v2(mag_ut=_bin("<f4", (5, 3), b"\x00" * 61)), "bad-shape"),
    (_v2(mag_ut=_bin("<f2", (5, 3))), "bad-dtype"),  # unknown dtype
    (_v2(mag_ut=_bin(">f4", (5, 3))), "bad-dtype"),  # big-endian
    (_v2(mag_ut={**_bin("<f4", (5, 3)), "dtype": ["<f4"]}), "bad-dtype"),
    (_v2(t_ns=_bin("<f8", (5,))), "bad-dtype"),  # times must be <i8
    (_v2(mag_ut=_f4([[np.nan, 0, 0]] + [[1, 2, 3]] * 4)), "non-finite"),  # NaN
    (_v2(acc_ms2=_f4([[np.inf, 0, 0]] * 5)), "non-finite"),
    (_v2(mag_ut=_f4([[1e7, 0, 0]] * 5)), "absurd-magnitude"),
    (_v2(gyr_rads=_f4([[0, 0, 500]] * 5)), "absurd-magnitude"),
    (_v2(mag_ut=_bin("<f4", (5, 4))), "bad-shape"),  # absurd shapes
    (_v2(mag_ut=_bin("<f4", (15,))), "bad-shape"),
    (_v2(mag_ut=_bin("<f4", (4, 3))), "bad-shape"),
    (_v2(mag_ut=_bin("<f4", (5, 3, 1))), "bad-shape"),
    (_v2(mag_ut={**_bin("<f4", (5, 3)), "shape": [-5, 3]}), "bad-shape"),
    (_v2(mag_ut={**_bin("<f4", (5, 3)), "shape": [5.0, 3]}), "bad-shape"),
    (_v2(mag_ut={**_bin("<f4", (5, 3)), "shape": "5x3"}), "bad-shape"),
    (_v2(mag_ut={**_bin("<f4", (5, 3)), "data": "text"}), "bad-shape"),
    (_v2(t_ns={"dtype": "<i8", "shape": [10**9], "data": b""}), "oversized"),
    (_v2(t_ns=_bin("<i8", (0,)), mag_ut=_bin("<f4", (0, 3)), acc_ms2=...), "empty"),
    (_v2(mag_ut=[[1.0, 2.0, 3.0]] * 5), "bad-shape"),  # v 1 lists in a v 2 message
    (_v2(mag_ut=...), "bad-shape"),
]


@pytest.mark.parametrize("payload, cause", MALFORMED_V2)
def test_malformed_v2_raw_is_refused_with_its_cause_alone_and_in_a_drain(payload, cause):
    with pytest.raises(wire.WireError) as info:
        wire.decode_raw(payload)
    assert info.value.cause == cause
    good = wire.encode_raw(wire.RawBatch("ok", 1, "sim", np.arange(3), np.ones((3, 3))))
    columns, errors = wire.decode_raw_many(
        [good, payload, wire.encode_raw(wire.RawBatch("ok1", 2, "sim", np.arange(2), np.ones((2, 3))), version=1)]
    )
    assert [(i, e.cause) for i, e in errors] == [(1, cause)]
    assert columns.devices == ["ok", "ok1"] and columns.counts.tolist() == [3, 2]


def test_malformed_v2_heading_is_refused():
    batch = wire.HeadingBatch(
        "dev",
        2,
        np.arange(3),
        np.zeros(3),
        np.zeros(3),
        np.zeros(3),
        np.zeros(3),
        np.ones((3, 3)),
        0.0,
        "",
        np.ones(3, dtype=int),
        np.tile([1.0, 0, 0, 0], (3, 1)),
    )
    message = msgpack.unpackb(wire.encode_heading(batch))
    for changes, cause in [
        ({"flags": _bin("<f4", (3,))}, "bad-dtype"),
        ({"field_ut": _bin("<f4", (3, 3), b"\x00")}, "bad-shape"),
        ({"heading_deg": {"dtype": "<f4", "shape": [3], "data": np.full(3, np.nan, "<f4").tobytes()}}, "non-finite"),
        (
            {"quat_wxyz": {"dtype": "<f4", "shape": [3, 4], "data": np.full((3, 4), 0.9, "<f4").tobytes()}},
            "absurd-magnitude",
        ),
        ({"pitch_deg": _bin("<f8", (2,))}, "bad-shape"),
    ]:
        with pytest.raises(wire.WireError) as info:
            wire.decode_heading(msgpack.packb({**message, **changes}))
        assert info.value.cause == cause


def test_v2_is_smaller_and_f8_arrays_are_read_too():
    batch = wire.RawBatch(
        "dev",
        1,
        "sim",
        np.arange(100) + 10**18,
        np.random.default_rng(1).normal(0, 40, (100, 3)),
        np.random.default_rng(2).normal(0, 9, (100, 3)),
    )
    assert len(wire.encode_raw(batch)) < 0.6 * len(wire.encode_raw(batch, version=1))
    message = msgpack.unpackb(wire.encode_raw(batch))
    message["mag_ut"] = {"dtype": "<f8", "shape": [100, 3], "data": batch.mag_ut.astype("<f8").tobytes()}
    np.testing.assert_array_equal(wire.decode_raw(msgpack.packb(message)).mag_ut, batch.mag_ut)


def test_plain_turns_v2_arrays_into_lists_for_printing():
    batch = wire.RawBatch("dev", 1, "sim", np.arange(2), np.array([[1.5, 2, 3], [4, 5, 6]]))
    shown = wire.plain(wire.unpack(wire.encode_raw(batch)))
    assert shown["mag_ut"] == [[1.5, 2.0, 3.0], [4.0, 5.0, 6.0]] and shown["t_ns"] == [0, 1]
    json.dumps(shown)
