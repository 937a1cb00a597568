"""The wire format: round trips, key shapes, and every kind of malformed message refused with a countable cause."""

import msgpack
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

from magnet import wire
from magnet.model import Calibration


def _raw(n=5, acc=True, truth=False, device="dev-1"):
    rng = np.random.default_rng(0)
    return wire.RawBatch(
        device,
        7,
        "lsm303dlh",
        np.arange(n, dtype=np.int64) * 10_000_000 + 1_700_000_000_000_000_000,
        rng.normal(0, 40, (n, 3)),
        rng.normal(0, 9.8, (n, 3)) if acc else None,
        {k: rng.uniform(0, 360, n) for k in ("heading_deg", "pitch_deg", "roll_deg")} if truth else None,
    )


finite = st.floats(-4000, 4000, allow_nan=False)


@settings(max_examples=40, deadline=None)
@given(mag=hnp.arrays(np.float64, st.tuples(st.integers(1, 60), st.just(3)), elements=finite), acc=st.booleans())
def test_raw_round_trip_is_exact_in_v1(mag, acc):
    n = mag.shape[0]
    batch = wire.RawBatch("d", 3, "sim", np.arange(n, dtype=np.int64), mag, mag / 100 if acc else None)
    back = wire.decode_raw(wire.encode_raw(batch, version=1))
    assert back.device == "d" and back.seq == 3 and back.sensor == "sim"
    np.testing.assert_array_equal(back.mag_ut, mag)
    np.testing.assert_array_equal(back.t_ns, np.arange(n))
    assert (back.acc_ms2 is None) == (not acc)


def test_raw_with_truth_keeps_truth_and_int64_times():
    batch = _raw(truth=True)
    back = wire.decode_raw(wire.encode_raw(batch))
    assert back.t_ns.dtype == np.int64 and back.t_ns[0] == batch.t_ns[0]
    np.testing.assert_allclose(back.truth["heading_deg"], batch.truth["heading_deg"])


def _mutate(**changes):
    message = msgpack.unpackb(wire.encode_raw(_raw(), version=1))
    message.update(changes)
    return msgpack.packb({k: v for k, v in message.items() if v is not ...})


@pytest.mark.parametrize(
    "payload, cause",
    [
        (b"\xc1garbage", "not-msgpack"),
        (msgpack.packb([1, 2, 3]), "not-a-map"),
        (_mutate(v=3), "wrong-version"),
        (_mutate(v=True), "wrong-version"),
        (_mutate(v=...), "wrong-version"),
        (_mutate(device="a/b"), "bad-device"),
        (_mutate(device=""), "bad-device"),
        (_mutate(mag_ut=[[1, 2]] * 5), "bad-shape"),
        (_mutate(mag_ut=[[1.0, 2.0, 3.0]] * 4), "bad-shape"),
        (_mutate(mag_ut=[[float("nan"), 2.0, 3.0]] * 5), "non-finite"),
        (_mutate(mag_ut=[[1e7, 2.0, 3.0]] * 5), "absurd-magnitude"),
        (_mutate(acc_ms2=[[1e6, 0, 0]] * 5), "absurd-magnitude"),
        (_mutate(t_ns=[1.5] * 5), "bad-shape"),
        (_mutate(t_ns=[], mag_ut=[], acc_ms2=None), "empty"),
        (_mutate(mag_ut="hello"), "bad-shape"),
        (_mutate(seq="x"), "bad-field"),
        (b"\x00" * (wire.MAX_PAYLOAD_BYTES + 1), "oversized"),
    ],
)
def test_malformed_raw_is_refused_with_its_cause(payload, cause):
    with pytest.raises(wire.WireError) as info:
        wire.decode_raw(payload)
    assert info.value.cause == cause


def test_gyro_round_trip_is_exact_and_optional():
    batch = wire.RawBatch(
        "d",
        1,
        "icm20948",
        np.arange(3),
        np.ones((3, 3)),
        None,
        gyr_rads=np.array([[0.1, -0.2, 3.0], [0, 0, 0], [-99.5, 1e-9, 2.5]]),
    )
    back = wire.decode_raw(wire.encode_raw(batch, version=1))
    np.testing.assert_array_equal(back.gyr_rads, batch.gyr_rads)
    assert back.acc_ms2 is None and wire.decode_raw(wire.encode_raw(_raw())).gyr_rads is None


@pytest.mark.parametrize(
    "gyr, cause",
    [
        ([[0.0, 0.0, 101.0]] * 5, "absurd-magnitude"),
        ([[0.0, float("nan"), 0.0]] * 5, "non-finite"),
        ([[0.0, 0.0]] * 5, "bad-shape"),
        ([[0.0, 0.0, 0.0]] * 4, "bad-shape"),
        ("fast", "bad-shape"),
    ],
)
def test_bad_gyro_is_refused_with_its_cause(gyr, cause):
    with pytest.raises(wire.WireError) as info:
        wire.decode_raw(_mutate(gyr_rads=gyr))
    assert info.value.cause == cause


def test_heading_quaternion_and_disturbance_flag():
    n = 3
    quat = np.array([[1.0, 0, 0, 0], [0.5, 0.5, 0.5, 0.5], [0, 0, 0, 1.0]])
    flags = np.array([1, 1 | 4, 1 | 8])
    batch = wire.HeadingBatch(
        "dev",
        2,
        np.arange(n),
        np.zeros(n),
        np.zeros(n),
        np.zeros(n),
        np.zeros(n),
        np.ones((n, 3)),
        0.0,
        "",
        flags,
        quat,
    )
    back = wire.decode_heading(wire.encode_heading(batch))
    np.testing.assert_array_equal(back.quat_wxyz, quat)
    assert back.disturbed.tolist() == [False, True, True]
    message = msgpack.unpackb(wire.encode_heading(batch))
    for bad in ([[2.0, 0, 0, 0]] * n, [[1.0, 0, 0]] * n, [[1.0, 0, 0, 0]] * (n - 1)):
        with pytest.raises(wire.WireError):
            wire.decode_heading(msgpack.packb({**message, "quat_wxyz": bad}))


def test_heading_round_trip():
    n = 4
    batch = wire.HeadingBatch(
        "dev",
        2,
        np.arange(n),
        np.full(n, 10.0),
        np.full(n, 15.0),
        np.zeros(n),
        np.ones(n),
        np.ones((n, 3)),
        5.0,
        "abc",
        np.array([1, 1, 3, 1]),
    )
    back = wire.decode_heading(wire.encode_heading(batch))
    np.testing.assert_array_equal(back.true_heading_deg, 15.0)
    assert back.calibration_id == "abc" and back.declination_deg == 5.0 and back.flags.tolist() == [1, 1, 3, 1]


def test_calibration_message_carries_record_id_and_time():
    cal = Calibration("ellipsoid", [1.0, 2.0, 3.0], np.diag([1.1, 0.9, 1.0]), field_strength=50.0)
    message = wire.decode_calibration(wire.encode_calibration("dev", cal, 123))
    assert message.device == "dev" and message.created_ns == 123 and message.id == cal.content_id
    np.testing.assert_allclose(message.calibration.offset, [1, 2, 3])
    record = msgpack.unpackb(wire.encode_calibration("dev", cal, 123))
    assert record["method"] == "ellipsoid" and record["id"] == cal.content_id and record["v"] == 1


@pytest.mark.parametrize(
    "changes, words",
    [
        ({"matrix": [[1, 0, 0], [0, 1, 0], [0, 0, 0]]}, "condition number"),
        ({"matrix": np.diag([1e9, 1, 1]).tolist()}, "condition number"),
        ({"matrix": [[-1, 0, 0], [0, 1, 0], [0, 0, 1]]}, "negative determinant"),
        ({"offset": [1e5, 0, 0]}, "offset"),
        ({"offset": [1, 2]}, "3 numbers"),
        ({"accepted": 1}, "true or false"),
    ],
)
def test_implausible_or_malformed_calibration_is_refused_on_the_wire(changes, words):
    record = wire.calibration_record("dev", Calibration("manual", [0, 0, 0], np.eye(3)), 1)
    for decode in (wire.calibration_from_record, lambda r: wire.decode_calibration(msgpack.packb(r))):
        with pytest.raises(wire.WireError, match=words) as info:
            decode({**record, **changes})
        assert info.value.cause == "bad-calibration"


@pytest.mark.parametrize("device", ["", "a/b", "a*", "$x", "q?", "h#", " lead", 5])
def test_bad_device_ids_are_refused(device):
    with pytest.raises(ValueError):
        wire.validate_device_id(device)


def test_keys_and_device_from_key():
    assert wire.key("magnet", "d1", wire.Kind.HISTORY) == "magnet/d1/calibration/history"
    assert wire.device_from_key("fleet/a", "fleet/a/d-9/raw", wire.Kind.RAW) == "d-9"
    with pytest.raises(wire.WireError):
        wire.device_from_key("magnet", "magnet/x/y/raw", wire.Kind.RAW)
    with pytest.raises(ValueError):
        wire.validate_prefix("magnet/*")


def test_drop_counter_reports_each_cause_once():
    counter = wire.DropCounter()
    assert [counter.count(c) for c in ("a", "a", "b", "a")] == [True, False, True, False]
    assert counter.counts == {"a": 3, "b": 1} and counter.total == 4
