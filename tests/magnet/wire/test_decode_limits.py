"""Bounded decoding: a msgpack bomb (a few MB that unpack to millions of objects) is refused by the limits of its
kind before it is built, fast and without memory to speak of; a refusal keeps no reference to the payload or to
what was unpacked (no traceback, no chained exception, no reference cycle); booleans are not numbers."""

import gc
import time
import tracemalloc

import msgpack
import numpy as np
import pytest

from magnet import wire
from magnet.calibration import FitInput
from magnet.drift.alerts import ALERT_LIMITS

FOUR_MB = 4 * 1024 * 1024


def _flat_bomb():
    """4 MB of msgpack holding one array of 4 million small integers (about 32 MB of pointers once built)."""
    payload = b"\xdd" + (FOUR_MB - 5).to_bytes(4, "big") + b"\x00" * (FOUR_MB - 5)
    assert len(payload) == FOUR_MB
    return payload


def _nested_bomb(size):
    """``size`` bytes of a map whose value is arrays of 10,000 empty arrays: one byte each, 70 bytes each once
    built (a 2.5 MB one is 180 MB of lists)."""
    inner = b"\xdd" + (10_000).to_bytes(4, "big") + b"\x90" * 10_000
    count = (size - 32) // len(inner)
    return b"\x81\xa3big\xdd" + count.to_bytes(4, "big") + inner * count


def _refusal(decode, payload):
    """The WireError ``decode(payload)`` raises, the seconds it took and the most memory traced while it ran again
    (bytes; tracing slows allocation, so it is timed untraced)."""
    start = time.perf_counter()
    with pytest.raises(wire.WireError) as info:
        decode(payload)
    seconds = time.perf_counter() - start
    tracemalloc.start()
    try:
        with pytest.raises(wire.WireError):
            decode(payload)
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    return info.value, seconds, peak


@pytest.mark.parametrize(
    "decode",
    [
        wire.decode_raw,
        wire.decode_heading,
        wire.decode_calibration,
        wire.decode_progress,
        lambda p: wire.unpack(p, ALERT_LIMITS),
        wire.unpack,  # a reply of no particular kind: ANY_LIMITS
    ],
)
def test_a_4mb_array_bomb_is_refused_before_it_is_built(decode):
    exc, seconds, peak = _refusal(decode, _flat_bomb())
    assert exc.cause == "oversized", str(exc)
    assert seconds < 0.2 and peak < 1_000_000


def test_the_array_bomb_is_refused_by_the_array_limit_when_the_size_would_pass():
    roomy = wire.RAW_LIMITS._replace(payload_bytes=2 * FOUR_MB)
    exc, seconds, peak = _refusal(lambda p: wire.unpack(p, roomy), _flat_bomb())
    assert exc.cause == "oversized" and "max_array_len" in str(exc)
    assert seconds < 0.2 and peak < 1_000_000


@pytest.mark.parametrize("limits", [wire.RAW_LIMITS])
def test_a_bomb_of_empty_arrays_is_stopped_by_the_count_of_entries(limits):
    payload = _nested_bomb(limits.payload_bytes)
    exc, seconds, peak = _refusal(lambda p: wire.unpack(p, limits), payload)
    assert exc.cause == "oversized" and "entries" in str(exc)
    # what was built before the count stopped it: ``containers`` empty lists (~70 bytes each), not 2.5 million
    assert peak < limits.containers * 100 + 1_000_000 and seconds < 1.0  # unbounded: 180 MB and seconds


@pytest.mark.parametrize("limits", [wire.RAW_LIMITS, wire.HEADING_LIMITS, wire.ANY_LIMITS])
@pytest.mark.parametrize("levels", [1000, 2000])
def test_nested_array_headers_cut_short_set_nothing_aside(limits, levels):
    """5 kB of headers that each declare a long array, then nothing: msgpack alone sets aside about 80 kB per
    level (80 MB, 0.1 s) before it finds the payload cut short; the walk without building refuses it first."""
    payload = (b"\xdd" + limits.array.to_bytes(4, "big")) * levels
    exc, seconds, peak = _refusal(lambda p: wire.unpack(p, limits), payload)
    assert exc.cause == "not-msgpack" and "whole" in str(exc)
    assert peak < 1_000_000 and seconds < 0.05


@pytest.mark.parametrize("size", [20, 20_000])  # small ones are left to msgpack, larger ones walked first
def test_trailing_bytes_after_a_whole_message_are_refused(size):
    payload = wire.pack({"device": "d", "pad": "x" * size}) + b"\x90"
    with pytest.raises(wire.WireError) as info:
        wire.unpack(payload, wire.RAW_LIMITS._replace(text=size))
    assert info.value.cause == "not-msgpack"


def test_no_array_may_declare_more_entries_than_the_payload_has_bytes():
    """A small payload is not walked: its arrays are bounded by its size instead (600 bytes of cut-short headers
    set aside under 1 MB, not 200 levels of 80 kB)."""
    payload = (b"\xdc" + (10_000).to_bytes(2, "big")) * 200
    exc, _, _ = _refusal(lambda p: wire.unpack(p, wire.RAW_LIMITS), payload)
    assert exc.cause == "oversized" and "max_array_len" in str(exc)
    payload = (b"\xdc" + (200).to_bytes(2, "big")) * 200  # within the size: cut short, a little set aside
    exc, _, peak = _refusal(lambda p: wire.unpack(p, wire.RAW_LIMITS), payload)
    assert exc.cause == "not-msgpack" and peak < 1_000_000


def test_honest_messages_of_the_largest_size_pass_the_limits():
    n = wire.MAX_BATCH_SAMPLES
    vec = np.full((n, 3), 12.5)
    truth = {name: np.zeros(n) for name in wire.TRUTH_FIELDS}
    batch = wire.RawBatch("d" * 128, 2**63 - 1, "s" * 64, np.arange(n), vec, vec, truth, vec, vel_ned_ms=vec)
    for version in (1, 2):
        assert len(wire.decode_raw(wire.encode_raw(batch, version=version))) == n
    quat = np.tile([1.0, 0.0, 0.0, 0.0], (n, 1))
    zeros = np.zeros(n)
    heading = wire.HeadingBatch("d" * 128, 1, np.arange(n), zeros, zeros, zeros, zeros, vec, 3.0, "c" * 16, zeros, quat)
    for version in (1, 2):
        assert len(wire.decode_heading(wire.encode_heading(heading, version=version))) == n


def test_a_refusal_keeps_nothing_alive():
    """A map that unpacks (within the limits) and is then refused: once the caller drops the errors, every byte of
    it is free without the garbage collector (no traceback, no chained exception, no cycle holding it)."""
    extra = {f"x{i}": [0] * 5_000 for i in range(wire.raw_header.MAX_EXTRA_FIELDS + 1)}
    message = {"v": 1, "device": "dev", "t_ns": list(range(10_000)), **extra}
    payload = msgpack.packb(message)
    gc.collect()
    gc.disable()
    tracemalloc.start()
    try:
        before, _ = tracemalloc.get_traced_memory()
        columns, errors = wire.decode_raw_many([payload])
        assert [e.cause for _, e in errors] == ["too-many-fields"]
        assert all(e.__traceback__ is None and e.__context__ is None for _, e in errors)
        with pytest.raises(wire.WireError) as info:
            wire.decode_raw(payload)
        assert info.value.__context__ is None
        del columns, errors, info
        after, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
        gc.enable()
    assert peak > 1_000_000  # it was built (about 1.4 MB of lists)...
    assert after - before < 200_000  # ... and all of it freed by reference counting alone


@pytest.mark.parametrize("field", ["t_ns", "mag_ut", "acc_ms2"])
def test_raw_v1_booleans_are_not_numbers(field):
    message = msgpack.unpackb(wire.encode_raw(wire.RawBatch("dev", 1, "s", np.arange(3), np.ones((3, 3))), version=1))
    message["acc_ms2"] = [[0.0, 0.0, 9.8]] * 3
    message[field] = [True, 1, 2] if field == "t_ns" else [[1.5, True, 0.0], [1.0, 2.0, 3.0], [False, 1.0, 2.0]]
    with pytest.raises(wire.WireError) as info:
        wire.decode_raw(msgpack.packb(message))
    assert info.value.cause == "bad-shape" and "true/false" in str(info.value)
    columns, errors = wire.decode_raw_many([msgpack.packb(message)])
    assert [e.cause for _, e in errors] == ["bad-shape"] and not columns.devices


@pytest.mark.parametrize("field", ["t_ns", "heading_deg", "field_ut", "flags"])
def test_heading_v1_booleans_are_not_numbers(field):
    n = 2
    zeros = np.zeros(n)
    batch = wire.HeadingBatch("dev", 1, np.arange(n), zeros, zeros, zeros, zeros, np.ones((n, 3)), 0.0, "c", zeros)
    message = msgpack.unpackb(wire.encode_heading(batch, version=1))
    message[field] = [[True, 1.0, 2.0], [1.0, 2.0, 3.0]] if field == "field_ut" else [False, 1]
    with pytest.raises(wire.WireError) as info:
        wire.decode_heading(msgpack.packb(message))
    assert info.value.cause == "bad-shape"


@pytest.mark.parametrize(
    ("field", "value"),
    [
        ("mag_ut", [["1e3", 0.0, 0.0], [1.0, 2.0, 3.0], [1.0, 2.0, 3.0]]),  # numpy alone reads "1e3" as 1000
        ("current_a", ["2.5", 1.0, 1.0]),
        ("truth", {"heading_deg": ["10", 0.0, 0.0], "pitch_deg": [0.0] * 3, "roll_deg": [0.0] * 3}),
        ("t_ns", [1, "2", 3]),
    ],
)
def test_raw_v1_strings_are_not_numbers_in_any_array(field, value):
    """One check of v 1 arrays for every field of both decoders (samples, scalars, truth)."""
    message = msgpack.unpackb(wire.encode_raw(wire.RawBatch("dev", 1, "s", np.arange(3), np.ones((3, 3))), version=1))
    message[field] = value
    with pytest.raises(wire.WireError) as info:
        wire.decode_raw(msgpack.packb(message))
    assert info.value.cause == "bad-shape", str(info.value)
    assert field == "t_ns" or "str where numbers belong" in str(info.value)


@pytest.mark.parametrize("field", ["heading_deg", "field_ut", "quat_wxyz"])
def test_heading_v1_strings_are_not_numbers(field):
    n = 2
    zeros, quat = np.zeros(n), np.tile([1.0, 0.0, 0.0, 0.0], (n, 1))
    field_ut = np.ones((n, 3))
    batch = wire.HeadingBatch("dev", 1, np.arange(n), zeros, zeros, zeros, zeros, field_ut, 0.0, "c", zeros, quat)
    message = msgpack.unpackb(wire.encode_heading(batch, version=1))
    values = message[field]
    message[field] = ["1", *values[1:]] if field == "heading_deg" else [["1", *values[0][1:]], *values[1:]]
    with pytest.raises(wire.WireError, match="str where numbers belong"):
        wire.decode_heading(msgpack.packb(message))


def test_integers_beyond_int64_are_out_of_range_in_both_decoders():
    message = msgpack.unpackb(wire.encode_raw(wire.RawBatch("dev", 1, "s", np.arange(2), np.ones((2, 3))), version=1))
    message["t_ns"] = [1, 2**64 - 1]
    payload = msgpack.packb(message)
    with pytest.raises(wire.WireError) as info:
        wire.decode_raw(payload)
    _, errors = wire.decode_raw_many([payload, payload])
    assert info.value.cause == "out-of-range" and [e.cause for _, e in errors] == ["out-of-range"] * 2


def test_real_records_fit_well_within_the_calibration_limits():
    from magnet.calibration import fit
    from magnet.simulator import SensorErrors, SimulatorConfig, simulate

    run = simulate(SimulatorConfig(count=600, seed=1, errors=SensorErrors(hard_iron_ut=np.array([20.0, -5.0, 3.0]))))
    for method in ("ellipsoid", "ellipsoid+align", "minmax2d"):
        calibration = fit(FitInput(run.mag_ut, acc=run.acc_ms2, field_ut=50.0), method)
        calibration = calibration.replace(reason="a reason in words " * 50)
        payload = wire.encode_calibration("d" * 128, calibration, 2**62)
        assert len(payload) * 8 < wire.CALIBRATION_LIMITS.payload_bytes
        record = msgpack.unpackb(payload)
        assert len(record) * 4 < wire.CALIBRATION_LIMITS.map
        assert wire.decode_calibration(payload).calibration.method == method


def test_the_kept_walker_gives_a_fresh_unpackers_verdict_whatever_came_before():
    """The whole-payload walk reuses one Unpacker per thread (codec._walk_small): after payloads cut short, with
    trailing bytes, too deep or not msgpack at all, each payload still gets the verdict of a fresh Unpacker."""
    from magnet.wire import codec

    def fresh(payload: bytes) -> bool:
        unpacker = msgpack.Unpacker(max_buffer_size=len(payload))
        unpacker.feed(payload)
        try:
            unpacker.skip()
        except Exception:
            return True
        return unpacker.tell() != len(payload)

    whole = msgpack.packb({"v": 2, "data": b"x" * 3000, "rows": list(range(300))})
    deep = b"\x91" * 2000 + b"\xc0"
    payloads = [whole, whole[:-7], whole + b"\x00", deep, b"\xc1" * 1200, whole, whole[:1500], whole, whole * 2]
    rng = np.random.default_rng(7)
    payloads += [bytes(rng.integers(0, 256, 1500, dtype=np.uint8)) for _ in range(20)] + [whole]
    assert [codec._walk_small(p, len(p)) for p in payloads] == [fresh(p) for p in payloads]
    assert not codec._walk_small(whole, len(whole)) and codec._WALKER.unpacker is not None  # kept after a whole one
