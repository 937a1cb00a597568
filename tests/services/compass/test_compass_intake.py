"""The compass's raw queue, bounded in bytes, without a network: payloads beyond a raw message's size are never
copied, the queue never holds more than its bytes, every message that goes no further is counted by cause, and a
drain takes at most its bytes (but always one message)."""

from __future__ import annotations

import logging
import threading

import pytest
from fake_channel import ClosedError, FakeChannel

from magnet import wire
from services.compass import intake as intake_module
from services.compass.intake import ENTRY_BYTES, SEGMENT_BYTES, PayloadIntake

LOG = logging.getLogger("test.compass.intake")


class Payload:
    """Stands in for zenoh.ZBytes: a length, and bytes only when asked (counted)."""

    copies = 0

    def __init__(self, size: int) -> None:
        self.size = size

    def __len__(self) -> int:
        return self.size

    def to_bytes(self) -> bytes:
        Payload.copies += 1
        return b"x" * self.size


class Sample:
    def __init__(self, device: str, size: int) -> None:
        self.key_expr = f"magnet/{device}/raw"
        self.payload = Payload(size)


class Numbered:
    """A payload whose bytes say which message it is (to check what comes out, in order)."""

    def __init__(self, i: int, size: int) -> None:
        self.data = (f"{i}:".encode() + bytes(range(256)) * (size // 256 + 1))[:size]

    def __len__(self) -> int:
        return len(self.data)

    def to_bytes(self) -> bytes:
        return self.data


def test_oversized_payloads_are_dropped_without_being_copied():
    intake = PayloadIntake(max_bytes=10_000, max_payload=1_000)
    Payload.copies = 0
    intake.offer_many([Sample("a", 1_001), Sample("b", 1_000), Sample("c", 4_000_000)])
    assert Payload.copies == 1 and [key for key, _ in intake.take(10, 10**9)] == ["magnet/b/raw"]
    drops = wire.DropCounter()
    intake.hand_over_drops(drops, LOG)
    assert drops.counts == {"raw:oversized": 2}
    assert intake.figures()["raw_messages"] == 3


def test_the_queue_never_holds_more_than_its_bytes_and_counts_what_did_not_fit():
    intake = PayloadIntake(max_bytes=3 * (1_000 + ENTRY_BYTES), max_payload=1_000)
    Payload.copies = 0
    intake.offer_many([Sample(f"d{i}", 1_000) for i in range(5)])
    intake.offer_many([Sample("tiny", 1)])  # full is full, however small
    assert len(intake) == 3 and Payload.copies == 3
    assert intake.queued_bytes == intake.high_water_bytes == 3 * (1_000 + ENTRY_BYTES) <= intake.max_bytes
    drops = wire.DropCounter()
    intake.hand_over_drops(drops, LOG)
    intake.hand_over_drops(drops, LOG)  # handed over once
    assert drops.counts == {"raw:queue-full": 3}
    # arrived = queued + dropped, to the message
    assert intake.figures()["raw_messages"] == len(intake) + drops.total == 6


def test_a_drain_takes_at_most_its_bytes_but_always_one_message_and_frees_the_room():
    intake = PayloadIntake(max_bytes=100_000, max_payload=10_000)
    intake.offer_many([Sample("big", 10_000), Sample("a", 100), Sample("b", 100), Sample("c", 100)])
    assert [key for key, _ in intake.take(100, max_bytes=50)] == ["magnet/big/raw"]  # one, however large
    assert [key for key, _ in intake.take(100, max_bytes=250)] == ["magnet/a/raw", "magnet/b/raw"]
    assert [key for key, _ in intake.take(1, max_bytes=10**9)] == ["magnet/c/raw"]
    assert intake.take(10, 10**9) == [] and intake.queued_bytes == 0
    high = 10_300 + 4 * ENTRY_BYTES
    assert intake.figures() == {"raw_messages": 4, "queued": 0, "queued_bytes": 0, "queue_high_water_bytes": high}


def test_the_pump_moves_everything_until_the_channel_closes():
    intake = PayloadIntake(max_bytes=1_000_000, max_payload=1_000)
    samples = [Sample(f"d{i}", 10) for i in range(2_500)]
    thread = threading.Thread(target=intake.pump, args=(FakeChannel(samples), ClosedError, 1024))
    thread.start()
    thread.join(timeout=10)
    assert not thread.is_alive()
    assert len(intake) == intake.figures()["raw_messages"] == 2_500


def test_a_queue_that_cannot_hold_one_raw_message_is_refused():
    with pytest.raises(ValueError, match="at least one of the largest raw messages"):
        PayloadIntake(max_bytes=wire.RAW_LIMITS.payload_bytes)


def test_the_allocator_is_told_to_give_freed_memory_back_on_glibc():
    import platform

    from services.common.allocator import give_back_freed_memory

    assert give_back_freed_memory() == (platform.libc_ver()[0] == "glibc")


def test_the_loop_waits_for_an_arrival_and_not_while_messages_wait():
    intake = PayloadIntake(max_bytes=1_000_000, max_payload=1_000)
    assert not intake.wait(0.0)  # nothing waits: waited (0 s here) for an arrival
    arrival = threading.Timer(0.05, intake.offer_many, args=([Sample("a", 10)],))
    arrival.start()
    assert intake.wait(10.0)  # woken by the arrival, long before the 10 s
    arrival.join()
    intake.offer_many([Sample("b", 10)])
    assert intake.wait(10.0) and len(intake.take(1, 10**9)) == 1  # one still waits: at once
    assert intake.wait(10.0) and len(intake.take(5, 10**9)) == 1
    assert not intake.wait(0.0)  # all taken


def test_a_backlog_is_kept_as_bytes_in_segments_each_unmapped_once_read_out():
    intake = PayloadIntake(max_bytes=16 * 1024 * 1024, max_payload=2_000_000)
    sizes = [199 + (i % 7) * 50 for i in range(20_000)] + [1_500_000, 40]  # a flood's backlog, then a large one
    samples = [Sample(f"flood-{i}", 0) for i in range(len(sizes))]
    for i, (sample, size) in enumerate(zip(samples, sizes)):
        sample.payload = Numbered(i, size)  # type: ignore[assignment]
    for start in range(0, len(samples), 1024):
        intake.offer_many(samples[start : start + 1024])
    assert len(intake) == len(sizes)
    segments = len(intake._segments)
    written = sum(intake_module.HEADER.size + len(s.key_expr) + size for s, size in zip(samples, sizes))
    assert segments <= written // SEGMENT_BYTES + 3  # 9 MB in segments of 1 MiB (the large one in its own), no more
    assert not any(isinstance(o, tuple) for o in intake.__dict__.values())  # no object per message
    out: list[tuple[str, bytes]] = []
    while batch := intake.take(3_000, 8 * 1024 * 1024):
        out += batch
        assert len(intake._segments) <= segments  # read-out segments go as the backlog drains
    assert out == [(s.key_expr, s.payload.to_bytes()) for s in samples]  # every message, whole and in order
    assert len(intake) == intake.queued_bytes == 0 and intake.figures()["queue_high_water_bytes"] > 5_000_000
    kept = list(intake._segments)
    assert len(kept) == 1 and kept[0].size == SEGMENT_BYTES  # one segment kept for what comes next
    intake.offer_many([Sample("again", 100)])
    assert intake._segments[0] is kept[0] and intake.take(5, 10**9) == [("magnet/again/raw", b"x" * 100)]


def test_a_long_key_counts_its_own_length():
    intake = PayloadIntake(max_bytes=10_000, max_payload=1_000)
    long_device = "d" * 2_000
    intake.offer_many([Sample(long_device, 10)])
    assert intake.queued_bytes == 10 + intake_module.HEADER.size + len(f"magnet/{long_device}/raw")
    assert intake.take(1, 10**9)[0][0] == f"magnet/{long_device}/raw" and intake.queued_bytes == 0
