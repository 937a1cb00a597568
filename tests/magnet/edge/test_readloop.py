"""The bounded read loop (magnet.edge.readloop) with a fake clock: backoff bounded, errors counted, health and
recovery."""

import dataclasses
import errno

import numpy as np
import pytest

from magnet.drivers.base import NOT_READY, Reading, SensorReadError
from magnet.drivers.hmc5883l import HMC5883L
from magnet.edge.readloop import STALLED, ReadLoop
from magnet.emulators.base import ConstantSource, FaultInjector
from magnet.emulators.hmc5883l import HMC5883LEmulator
from magnet.retry import READ_BACKOFF, RetryPolicy

GOOD = Reading(mag_ut=np.array([20.0, 0.0, 45.0]))


class FakeClock:
    """A clock that only moves when slept on; records every sleep."""

    def __init__(self) -> None:
        self.t = 0.0
        self.sleeps: list[float] = []

    def __call__(self) -> float:
        return self.t

    def sleep(self, seconds: float) -> None:
        self.sleeps.append(seconds)
        self.t += seconds


class Script:
    """A sensor's read(): each item is a Reading to return or an errno to raise; the last item repeats."""

    def __init__(self, *items) -> None:
        self.items, self.calls = list(items), 0

    def __call__(self) -> Reading:
        item = self.items[min(self.calls, len(self.items) - 1)]
        self.calls += 1
        if isinstance(item, int):
            raise SensorReadError(item, "read failed")
        return item


def make_loop(read, clock, **backoff):
    changes = []
    loop = ReadLoop(
        read,
        clock=clock,
        sleep=clock.sleep,
        policy=dataclasses.replace(READ_BACKOFF, **backoff),
        on_health=lambda healthy, error: changes.append((healthy, error)),
    )
    return loop, changes


def test_dead_sensor_backs_off_exponentially_capped_and_counts_every_error():
    clock = FakeClock()
    loop, changes = make_loop(Script(errno.EIO), clock, initial_s=0.01, max_s=1.0, unhealthy_after=3)
    assert loop.next(stop=lambda: clock.t >= 60.0) is None
    assert clock.sleeps[:4] == pytest.approx([0.01, 0.02, 0.04, 0.08])
    assert max(clock.sleeps) == 1.0 and clock.sleeps[-5:] == [1.0] * 5
    health = loop.health
    assert health.attempts <= 70  # about one attempt per max_s once backed off
    assert health.errors == health.attempts and health.errors_by_cause == {"EIO": health.errors}
    assert not health.healthy and changes == [(False, "[Errno 5] read failed")]
    assert health.waited_s == pytest.approx(clock.t)


def test_recovery_makes_it_healthy_again_and_restarts_the_backoff():
    clock = FakeClock()
    loop, changes = make_loop(Script(*[errno.EIO] * 5, GOOD, errno.EBUSY, GOOD), clock, unhealthy_after=3)
    assert loop.next() is GOOD
    assert loop.health.errors == 5 and loop.health.samples == 1 and loop.health.healthy
    assert [healthy for healthy, _ in changes] == [False, True]
    clock.sleeps.clear()
    assert loop.next() is GOOD
    assert clock.sleeps == [0.01]  # one failure: the first step of the backoff
    assert loop.health.errors_by_cause == {"EIO": 5, "EBUSY": 1} and len(changes) == 2


def test_fewer_failures_than_the_threshold_stay_healthy():
    clock = FakeClock()
    loop, changes = make_loop(Script(errno.EIO, errno.EIO, GOOD), clock, unhealthy_after=3)
    assert loop.next() is GOOD and loop.health.healthy and changes == []


def test_not_ready_is_polled_and_a_stalled_chip_counts_as_a_failure():
    clock = FakeClock()
    loop, _ = make_loop(Script(NOT_READY, NOT_READY, GOOD), clock, poll_s=0.001)
    assert loop.next() is GOOD and loop.health.not_ready == 2 and loop.health.errors == 0
    assert clock.sleeps == [0.001, 0.001]
    stalled, _ = make_loop(Script(*[NOT_READY] * 10, GOOD), clock, poll_s=0.0, max_polls=4)
    assert stalled.next() is GOOD
    assert stalled.health.errors_by_cause == {STALLED: 2} and stalled.health.not_ready == 10


def test_overflow_is_counted_and_skipped():
    clock = FakeClock()
    loop, _ = make_loop(Script(Reading(overflow=True), GOOD), clock)
    assert loop.next() is GOOD and loop.health.overflows == 1 and loop.health.attempts == 2


def test_give_up_after_raises_a_clear_error():
    clock = FakeClock()
    loop, _ = make_loop(Script(errno.ETIMEDOUT), clock, give_up_after=5)
    with pytest.raises(SensorReadError, match=r"no usable reading after 5 failures in a row over 0\.15 s"):
        loop.next()
    assert loop.health.attempts == 5


def test_stop_is_checked_before_every_attempt():
    read = Script(GOOD)
    loop, _ = make_loop(read, FakeClock())
    assert loop.next(stop=lambda: True) is None and read.calls == 0


@pytest.mark.parametrize(
    "bad,message",
    [
        (dict(initial_s=2.0, max_s=1.0), "initial_s <= max_s"),
        (dict(factor=0.5), "factor must be >= 1"),
        (dict(unhealthy_after=0), "unhealthy_after"),
        (dict(give_up_after=0), "give_up_after"),
        (dict(poll_s=-1), "poll_s >= 0"),
    ],
)
def test_bad_backoff_is_refused(bad, message):
    with pytest.raises(ValueError, match=message):
        RetryPolicy(**bad)


def test_a_driver_on_a_dead_emulated_bus_through_the_loop():
    faults = FaultInjector()
    sensor = HMC5883L(HMC5883LEmulator(ConstantSource(), faults=faults), sleep=lambda s: None)
    faults.probability = 1.0  # the bus dies after set-up
    clock = FakeClock()
    loop, changes = make_loop(sensor.read, clock, max_s=0.5)
    assert loop.next(stop=lambda: clock.t >= 10.0) is None
    assert loop.health.attempts <= 30 and loop.health.errors == loop.health.attempts
    # each failed read is one transfer that failed its every try
    assert sensor.health.errors - sensor.health.retries == loop.health.errors and not sensor.health.healthy
    faults.probability = 0.0  # the bus comes back
    reading = loop.next()
    assert reading is not None and np.allclose(reading.mag_ut, [20.0, 0.0, 45.0], atol=0.5)
    assert [healthy for healthy, _ in changes] == [False, True] and sensor.health.healthy


def test_one_policy_and_one_health_record_serve_the_transfer_and_the_read_loop():
    """The driver's I2C transfers and the read loop share RetryPolicy and Health (magnet.retry); a transfer's policy
    must give up, or a dead bus would hang a read."""
    from magnet.drivers.base import I2CDevice
    from magnet.retry import TRANSFER_RETRY, Health

    assert [TRANSFER_RETRY.delay_s(n) for n in (1, 2, 3)] == [0.002, 0.004, 0.008]
    assert [READ_BACKOFF.delay_s(n) for n in (1, 2, 8, 20)] == [0.01, 0.02, 1.0, 1.0]
    assert TRANSFER_RETRY.gives_up(4) and not READ_BACKOFF.gives_up(10**6)
    with pytest.raises(ValueError, match="must give up"):
        I2CDevice(HMC5883LEmulator(ConstantSource()), 0x1E, retry=READ_BACKOFF)
    health = Health()
    policy = RetryPolicy(unhealthy_after=2)
    assert [health.failed("EIO", "x", policy), health.failed("EIO", "y", policy)] == [False, True]
    assert not health.failed("EBUSY", "z", policy) and health.errors_by_cause == {"EIO": 2, "EBUSY": 1}
    assert health.succeeded() and not health.succeeded() and health.healthy and health.consecutive_failures == 0
    sensor = HMC5883L(HMC5883LEmulator(ConstantSource()), sleep=lambda s: None)
    assert isinstance(sensor.health, Health) and isinstance(make_loop(sensor.read, FakeClock())[0].health, Health)
