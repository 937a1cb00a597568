"""Issue 32: ``magnet edge --ros2`` on a wrong topic reported healthy with 0 samples, and published field stamps that
ran backwards without a word. In-process: the source's subscriptions replaced by a list of payloads (no network)."""

from __future__ import annotations

import logging

import numpy as np
import pytest

from magnet.ros2 import messages
from services.common.ros2_options import Ros2Settings
from services.edge import ros2_source
from services.edge.ros2_source import Ros2Source
from services.edge.settings import EdgeSettings


class Payload:
    def __init__(self, data: bytes) -> None:
        self.data = data

    def to_bytes(self) -> bytes:
        return self.data


class Sample:
    def __init__(self, data: bytes) -> None:
        self.payload = Payload(data)


class Channel:
    def __init__(self) -> None:
        self.items: list[Sample] = []

    def try_recv(self) -> Sample | None:
        return self.items.pop(0) if self.items else None


class Events:
    def __init__(self) -> None:
        self.told: list[tuple[bool, str]] = []

    def on_health(self, healthy: bool, error: str) -> None:
        self.told.append((healthy, error))


def source() -> tuple[Ros2Source, Channel, Events]:
    src = Ros2Source(EdgeSettings(ros2=Ros2Settings(enabled=True), mag_topic="/robot/wrong", device="r1", batch=2))
    channel, events = Channel(), Events()
    src.subs[messages.MAGNETIC_FIELD] = channel  # type: ignore[assignment]
    src.events = events  # type: ignore[assignment]
    return src, channel, events


def field(t_ns: list[int]) -> list[Sample]:
    values = np.tile([20e-6, 0.0, -40e-6], (len(t_ns), 1))
    return [Sample(b) for b in messages.magnetic_field_cdr(np.array(t_ns), "m", values, 0.0)]


def test_a_topic_with_no_samples_turns_the_source_unhealthy_and_a_sample_heals_it() -> None:
    src, channel, events = source()
    start = src.last_sample_s
    src.watch(start + ros2_source.SILENT_S - 1)
    assert src.status()["healthy"] and events.told == []
    src.watch(start + ros2_source.SILENT_S + 1)
    status = src.status()
    assert not status["healthy"] and "/robot/wrong" in status["last_error"] and "0 in all" in status["last_error"]
    assert events.told == [(False, status["last_error"])]
    channel.items += field([1_000])
    src._take(messages.MAGNETIC_FIELD, 0.0)
    src.watch(start + ros2_source.SILENT_S + 2)
    assert src.status()["healthy"] and events.told[-1][0] is True


def test_field_stamps_that_run_backwards_are_counted_and_said_once(caplog: pytest.LogCaptureFixture) -> None:
    src, channel, _ = source()
    channel.items += field([1_000_000, 2_000_000, 1_500_000, 900_000, 3_000_000, 4_000_000])
    stop = iter([False, False, True])
    with caplog.at_level(logging.WARNING, logger="magnet.edge.ros2"):
        out = [b for batches in src.batches(lambda: next(stop)) for b in batches]
    assert [t for b in out for t in b.t_ns.tolist()] == [1_000_000, 2_000_000, 3_000_000, 4_000_000]
    assert src.status()["errors_by_cause"]["mag-backwards"] == 2
    said = [r.getMessage() for r in caplog.records if "mag-backwards" in r.getMessage()]
    assert len(said) == 1 and "ran backwards" in said[0]
