"""The calibrator's bounded sample path without a network: the queue drops and counts beyond its bound, the
enrolment bucket admits new ids at its rate, and the service loop answers queries between slices of samples."""

from __future__ import annotations

from fake_channel import ClosedError, FakeChannel

from services.calibrator.intake import Enrolment, RawIntake, new_device


def test_the_queue_is_bounded_and_counts_every_message_it_drops():
    intake = RawIntake(max_queue=3)
    offered = [intake.offer(f"magnet/d{i}/raw", b"x") for i in range(5)]
    assert offered == [True, True, True, False, False]
    assert (intake.raw_messages, intake.queue_full, len(intake), intake.high_water) == (5, 2, 3, 3)
    assert [key for key, _ in intake.take(2)] == ["magnet/d0/raw", "magnet/d1/raw"]
    assert intake.offer("magnet/d5/raw", b"x") and len(intake) == 2


def test_enrolment_admits_a_burst_then_the_rate():
    now = [0.0]
    bucket = Enrolment(rate_per_s=10, burst=5, clock=lambda: now[0])
    assert sum(bucket.admit() for _ in range(20)) == 5  # the burst
    now[0] = 1.0
    assert sum(bucket.admit() for _ in range(20)) == 5  # one second of the rate, capped at the burst
    now[0] = 1.25
    assert sum(bucket.admit() for _ in range(20)) == 2
    assert (bucket.admitted, bucket.refused) == (12, 48)


def test_new_device_reads_the_key_and_leaves_malformed_keys_to_the_decoder():
    known = {"a"}.__contains__
    assert new_device("magnet/b/raw", "magnet", known)
    assert not new_device("magnet/a/raw", "magnet", known)
    assert not new_device("magnet/a/b/raw", "magnet", known)  # malformed: decoded, refused and counted there


class Sample:
    def __init__(self, i):
        self.key_expr, self.payload = f"magnet/d{i}/raw", bytes([i])


def test_the_pump_moves_batches_into_the_bounded_queue_until_the_channel_closes():
    intake = RawIntake(max_queue=4)
    channel = FakeChannel([Sample(0), Sample(1), None, Sample(2), Sample(3), Sample(4), Sample(5)])
    intake.pump(channel, lambda s: s.payload, ClosedError, batch=3)
    assert intake.raw_messages == 6 and intake.queue_full == 2 and len(intake) == 4
    assert [key for key, _ in intake.take(10)] == [f"magnet/d{i}/raw" for i in range(4)]
