"""The compass's outputs are its sinks (``services.compass.sinks``): every drain reaches each sink turned on, in the
order of ``SINKS``, then their ticks; a new sink is one class and one line; closing closes them, the last first."""

from __future__ import annotations

from typing import Any, ClassVar

import numpy as np
from compass_steps import compass_core

from magnet import wire
from magnet.earth.expected import Earth
from services.compass import service as compass_service
from services.compass import sinks
from services.compass.ros2 import Ros2Compass

PREFIX = "magnet"


class FakeSession:
    def __init__(self) -> None:
        self.puts: list[tuple[str, bytes]] = []

    def put(self, key: str, payload: bytes) -> None:
        self.puts.append((key, payload))

    def get(self, *args: Any, **kwargs: Any) -> list[Any]:
        return []


class RecordingSink:
    """A newcomer's sink: it keeps what it was given."""

    events: ClassVar[list[str]] = []

    def __init__(self, name: str) -> None:
        self.name = name
        self.drains: list[tuple[list[str], np.ndarray]] = []

    @classmethod
    def open(cls, session: Any, settings: Any) -> RecordingSink:
        return cls("recording")

    def publish(self, columns: wire.RawColumns, out: Any, core: Any) -> None:
        self.events.append("publish")
        self.drains.append((list(columns.devices), out.true_heading_deg.copy()))

    def tick(self, core: Any) -> None:
        self.events.append("tick")

    def close(self) -> None:
        self.events.append("close")


def _raw(device: str, seq: int) -> tuple[str, bytes]:
    rng = np.random.default_rng(seq)
    mag, acc = rng.normal(size=(10, 3)) * 40, np.tile([0, 0, -9.8], (10, 1))
    return f"{PREFIX}/{device}/raw", wire.encode_raw(wire.RawBatch(device, seq, "sim", np.arange(10), mag, acc))


def _loop(monkeypatch: Any) -> tuple[Any, FakeSession]:
    monkeypatch.setattr(sinks, "SINKS", (*sinks.SINKS, RecordingSink.open))  # the one line
    session = FakeSession()
    loop = compass_service._Loop(session, compass_core(Earth(5.0), 1), compass_service.CompassSettings())
    return loop, session


def test_the_default_sinks_are_the_zenoh_headings_and_ros2_when_asked():
    assert (sinks.ZenohHeadings.open, Ros2Compass.open) == sinks.SINKS
    settings = compass_service.CompassSettings()
    assert Ros2Compass.open(FakeSession(), settings) is None  # type: ignore[arg-type]  # without --ros2
    opened = sinks.open_sinks(FakeSession(), settings)  # type: ignore[arg-type]
    assert [type(s) for s in opened] == [sinks.ZenohHeadings]


def test_a_new_sink_gets_every_drain_beside_the_heading_messages_and_is_closed(monkeypatch):
    RecordingSink.events = []
    loop, session = _loop(monkeypatch)
    recording = loop.sinks[-1]
    loop.headings_of([_raw("d1", 0), _raw("d2", 1)])
    loop.headings_of([_raw("d1", 2)])
    # the Zenoh sink: one heading message per raw batch, counted
    assert [key for key, _ in session.puts] == [f"{PREFIX}/d1/heading", f"{PREFIX}/d2/heading", f"{PREFIX}/d1/heading"]
    assert loop.core.counters.published_batches == 3
    # the new one: the same drains, in order, the headings those messages carry
    assert [devices for devices, _ in recording.drains] == [["d1", "d2"], ["d1"]]
    message = wire.decode_heading(session.puts[0][1])
    np.testing.assert_allclose(message.true_heading_deg, recording.drains[0][1][:10], atol=1e-4)  # float32 wire
    assert RecordingSink.events == ["publish", "tick", "publish", "tick"]
    loop.close()
    assert RecordingSink.events[-1] == "close"
