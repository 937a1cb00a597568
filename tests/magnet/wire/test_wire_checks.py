"""The raw checks against hostile peers: out-of-range or wrapped counters and times, time running backwards inside a
batch, oversized text, a flood of unknown keys and padded payloads are each dropped and counted with their cause, in
both versions, alone and among good messages in one drain."""

import msgpack
import numpy as np
import pytest

from magnet import wire
from magnet.wire.raw_header import MAX_BYTES_PER_SAMPLE, MAX_EXTRA_FIELDS, MAX_HEADER_BYTES, MAX_SENSOR_CHARS

INT64_MAX = 2**63 - 1
UINT64_MAX = 2**64 - 1


def _message(version=1, n=5, **changes):
    batch = wire.RawBatch("dev-1", 7, "lsm303dlh", np.arange(n, dtype=np.int64) * 10_000_000, np.ones((n, 3)))
    message = msgpack.unpackb(wire.encode_raw(batch, version=version))
    message.update(changes)
    return {k: v for k, v in message.items() if v is not ...}


def _times(values, version):
    """t_ns holding ``values``: a list (v 1) or an ``<i8`` array map (v 2)."""
    if version == 1:
        return list(values)
    return {"dtype": "<i8", "shape": [len(values)], "data": np.array(values, dtype="<i8").tobytes()}


def _refused(payload, cause):
    """Refused with ``cause`` alone, and alone of three in one drain (the good ones around it kept)."""
    with pytest.raises(wire.WireError) as info:
        wire.decode_raw(payload)
    assert info.value.cause == cause, str(info.value)
    good = [wire.encode_raw(wire.RawBatch(d, 1, "sim", np.arange(3), np.ones((3, 3)))) for d in ("a", "b")]
    columns, errors = wire.decode_raw_many([good[0], payload, good[1]])
    assert [(i, e.cause) for i, e in errors] == [(1, cause)]
    assert columns.devices == ["a", "b"]


def _packed(message):
    return msgpack.packb(message, use_bin_type=True)


@pytest.mark.parametrize("version", [1, 2])
@pytest.mark.parametrize("seq", [-1, -(2**63), INT64_MAX + 1, UINT64_MAX])
def test_negative_or_wrapped_seq_is_refused(version, seq):
    _refused(_packed(_message(version, seq=seq)), "out-of-range")


@pytest.mark.parametrize("version", [1, 2])
def test_largest_seq_and_time_are_kept(version):
    n = 3
    times = [INT64_MAX - 2, INT64_MAX - 1, INT64_MAX]
    batch = wire.decode_raw(_packed(_message(version, n=n, seq=INT64_MAX, t_ns=_times(times, version))))
    assert batch.seq == INT64_MAX and batch.t_ns.tolist() == times


@pytest.mark.parametrize("version", [1, 2])
@pytest.mark.parametrize("times", [[-1, 0, 1, 2, 3], [-(2**63)] * 5, [0, 1, 2, 3, -5]])
def test_negative_time_is_refused(version, times):
    _refused(_packed(_message(version, t_ns=_times(times, version))), "out-of-range")


def test_time_beyond_int64_is_refused_not_wrapped():
    """msgpack carries uint64: 2**63 and above would wrap to negative int64 (v 1 lists only: v 2 is ``<i8``)."""
    _refused(_packed(_message(1, t_ns=[INT64_MAX + 1, INT64_MAX + 2, UINT64_MAX, 5, 6])), "out-of-range")
    _refused(_packed(_message(1, t_ns=[1, 2, 3, 4, UINT64_MAX])), "out-of-range")


@pytest.mark.parametrize("version", [1, 2])
def test_time_running_backwards_in_a_batch_is_refused(version):
    _refused(_packed(_message(version, t_ns=_times([10, 20, 30, 25, 40], version))), "time-backwards")


@pytest.mark.parametrize("version", [1, 2])
def test_equal_times_and_a_later_batch_starting_earlier_are_kept(version):
    """Only time inside one batch is judged: a batch may repeat a time, and the next batch may start before the
    last one ended (another device, or a device whose clock was set)."""
    first = _packed(_message(version, t_ns=_times([10, 20, 20, 30, 40], version)))
    second = _packed(_message(version, t_ns=_times([0, 1, 2, 3, 4], version)))
    columns, errors = wire.decode_raw_many([first, second])
    assert errors == [] and columns.t_ns.tolist() == [10, 20, 20, 30, 40, 0, 1, 2, 3, 4]


@pytest.mark.parametrize("version", [1, 2])
def test_a_long_sensor_name_is_refused(version):
    assert wire.decode_raw(_packed(_message(version, sensor="s" * MAX_SENSOR_CHARS))).sensor == "s" * 64
    _refused(_packed(_message(version, sensor="s" * (MAX_SENSOR_CHARS + 1))), "bad-field")
    _refused(_packed(_message(version, sensor="s" * 1_000_000)), "oversized")  # beyond any string of a raw message


@pytest.mark.parametrize("version", [1, 2])
def test_a_flood_of_unknown_keys_is_refused(version):
    some = {f"x{i}": i for i in range(MAX_EXTRA_FIELDS)}
    assert wire.decode_raw(_packed(_message(version, **some))).device == "dev-1"  # room for new fields
    flood = {f"x{i}": i for i in range(MAX_EXTRA_FIELDS + 1)}
    _refused(_packed(_message(version, **flood)), "too-many-fields")
    _refused(_packed(_message(version, **{f"x{i}": i for i in range(1000)})), "oversized")  # a map too long to build


@pytest.mark.parametrize("version", [1, 2])
def test_a_padded_payload_is_refused(version):
    """A few samples padded with a large unknown field: more bytes than the samples can need."""
    pad = b"\x00" * (MAX_HEADER_BYTES + 5 * MAX_BYTES_PER_SAMPLE)
    _refused(_packed(_message(version, padding=pad)), "oversized")


def test_the_largest_honest_batch_fits_the_byte_budget():
    """A full batch in v 1 with float64 everywhere (the widest encoding) and the simulator's truth is not refused."""
    n = wire.MAX_BATCH_SAMPLES
    rng = np.random.default_rng(1)
    vectors = rng.uniform(-99.0, 99.0, (3, n, 3)) + 0.123456789
    truth = {k: rng.uniform(0, 360, n) + 0.123456789 for k in ("heading_deg", "pitch_deg", "roll_deg")}
    batch = wire.RawBatch(
        "d" * 64, INT64_MAX, "s" * 64, np.arange(n) + 2**62, vectors[0], vectors[1], truth, vectors[2]
    )
    payload = wire.encode_raw(batch, version=1)
    assert len(wire.decode_raw(payload)) == n


def test_a_stale_calibration_is_not_logged_as_malformed(caplog):
    """Issue 32: a well-formed calibration older than the one in force was logged as "malformed"."""
    import logging

    from magnet.wire.errors import DropCounter, WireError

    drops, logger = DropCounter(), logging.getLogger("test.drops")
    with caplog.at_level(logging.WARNING, logger="test.drops"):
        drops.drop(WireError("stale", "calibration c1 is not newer than c2"), "calibration", logger)
        drops.drop(WireError("not-msgpack", "garbage"), "raw", logger)
    assert "dropping stale calibration message (stale)" in caplog.messages[0]
    assert "malformed" not in caplog.messages[0] and "dropping malformed raw message" in caplog.messages[1]
    assert drops.counts == {"calibration:stale": 1, "raw:not-msgpack": 1}


def test_value_faults_are_the_plain_per_row_checks():
    """``value_faults`` (compiled: ``magnet._kernels.row_faults``) against the checks written plainly in numpy:
    a row with a non-finite value (unless all NaN, with ``absent_rows``), a row with a value beyond +-limit."""
    from magnet.wire.arrays import value_faults

    rng = np.random.default_rng(7)
    arr = rng.normal(0.0, 50.0, (500, 3))
    arr[rng.random((500, 3)) < 0.05] = np.nan
    arr[rng.random((500, 3)) < 0.02] = np.inf
    arr[rng.random((500, 3)) < 0.02] = -np.inf
    arr[::37] = np.nan  # absent rows
    for values in (arr, arr[:, 1], arr[:, :0], arr[::2, ::2]):
        for absent in (False, True):
            rows = values.reshape(len(values), -1)
            finite = np.isfinite(rows).all(axis=1) | (absent & np.isnan(rows).all(axis=1))
            beyond = (np.nan_to_num(np.abs(rows), nan=0.0) > 120.0).any(axis=1)
            (bad, cause, _), (over, cause_over, text) = value_faults(values, "mag_ut", 120.0, absent)
            np.testing.assert_array_equal(bad, ~finite)
            np.testing.assert_array_equal(over, beyond)
            assert (cause, cause_over, text) == ("non-finite", "absurd-magnitude", "mag_ut holds values beyond +-120")
            assert len(value_faults(values, "t", None, absent)) == 1


def test_a_flood_of_new_device_ids_is_not_kept_by_the_validation_cache() -> None:
    """Issue 32's soak: every service kept each device id it had validated, up to 100,000 of them, so each flood of
    20,000 new ids left about 1.3 MB more alive in the dashboard, calibrator and compass for five floods (found with
    the dashboard's rows held at 10,000 while its live objects grew). The ids of a flood are now let go."""
    import gc
    import tracemalloc

    wire.validate_device_id("real-1")
    gc.collect()
    tracemalloc.start()
    try:
        before = tracemalloc.get_traced_memory()[0]
        for i in range(50_000):  # three caches' worth and then some (the cap is 16,384)
            wire.validate_device_id(f"flood-{i}")  # each id string dropped by the caller at once
        gc.collect()
        kept = tracemalloc.get_traced_memory()[0] - before
    finally:
        tracemalloc.stop()
    # at most one cache's worth of ids (here 849 of them, 84 kB); every id kept, as before: 5.1 MB, and a cap of
    # 100,000 emptied only when full keeps as much (a flood of 100,000 would have emptied it just at its end)
    assert kept < 2_500_000, kept
    assert wire.validate_device_id("real-1") == "real-1"
    with pytest.raises(ValueError, match="may not contain"):
        wire.validate_device_id("flood/1")
