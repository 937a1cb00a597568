"""When a service loop gives its freed heap back (``allocator.BurstTrim``): every period, and during a burst at most
every ``busy_every_s`` and once after it; no network, an injected clock and trim."""

from __future__ import annotations

import pytest

from services.common.allocator import BurstTrim, give_back_now


class Clock:
    def __init__(self) -> None:
        self.now_s = 100.0

    def __call__(self) -> float:
        return self.now_s


def make() -> tuple[BurstTrim, Clock, list[float]]:
    clock, trims = Clock(), []
    trim = BurstTrim(500, every_s=10.0, busy_every_s=1.0, trim=lambda: trims.append(clock.now_s) or True, clock=clock)
    return trim, clock, trims


def test_quiet_steps_trim_only_every_period():
    trim, clock, trims = make()
    for _ in range(39):  # 9.75 s of quiet steps of a few messages
        clock.now_s += 0.25
        trim.after_step(3)
    assert trims == []
    clock.now_s += 0.25
    assert trim.after_step(3) and trims == [110.0]


def test_a_burst_trims_at_most_every_busy_period_and_once_after_it():
    trim, clock, trims = make()
    clock.now_s += 2.0
    assert trim.after_step(800)  # a burst, the last trim 2 s ago: at once
    for _ in range(10):  # 2.5 s more of the burst: one trim a second
        clock.now_s += 0.25
        trim.after_step(800)
    assert trims == [102.0, 103.0, 104.0]
    clock.now_s += 0.25
    trim.after_step(0)  # the burst is over; its last drains' heap not yet given back
    clock.now_s += 0.5
    assert trim.after_step(0) and len(trims) == 4  # once after it, a second after the last
    clock.now_s += 1.0
    assert not trim.after_step(0) and len(trims) == 4  # then only the period


def test_bad_settings_are_refused():
    with pytest.raises(ValueError, match="at least 1 message"):
        BurstTrim(0)
    with pytest.raises(ValueError, match="at most as far apart"):
        BurstTrim(10, every_s=1.0, busy_every_s=2.0)


def test_give_back_now_is_cheap_after_the_first_call():
    import platform
    import time

    give_back_now()
    started = time.perf_counter()
    for _ in range(10):
        assert give_back_now() == (platform.libc_ver()[0] == "glibc")
    assert time.perf_counter() - started < 0.5  # the library is looked up once, not every call


def test_a_burst_told_by_the_loop_trims_however_few_the_messages():
    trim, clock, trims = make()
    clock.now_s += 1.0
    assert trim.after_step(1, burst=True)  # e.g. bombs of MBs refused by their size: few messages, a heap of MBs
    clock.now_s += 0.5
    assert not trim.after_step(2, burst=True)  # more of them, within the second
    clock.now_s += 0.5
    assert trim.after_step(0) and len(trims) == 2  # their heap given back once after them
    clock.now_s += 1.0
    assert not trim.after_step(0) and len(trims) == 2
