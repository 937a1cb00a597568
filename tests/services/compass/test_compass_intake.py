"""The compass's raw queue, bounded in bytes, without a network: payloads beyond a raw message's size are never
copied, the queue never holds more than its bytes, every message that goes no further is counted by cause, and a
drain takes at most its bytes (but always one message)."""

from __future__ import annotations

import logging
import threading

import pytest
from fake_channel import ClosedError, FakeChannel

from magnet import wire
from services.compass.intake import ENTRY_BYTES, PayloadIntake

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


def test_oversized_payloads_are_dropped_without_being_copied():
    intake = PayloadIntake(max_bytes=10_000, max_payload=1_000)
    Payload.copies = 0
    intake.offer_many([Sample("a", 1_001), Sample("b", 1_000), Sample("c", 4_000_000)])
    assert Payload.copies == 1 and [key for key, _ in intake.queue] == ["magnet/b/raw"]
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
