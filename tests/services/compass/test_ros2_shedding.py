"""Issue 32: ``magnet compass --ros2`` hit with 12,000 new ids in 6 s left its status unanswered for 3.5 minutes, a
real device's ROS 2 output 237 s late and SIGTERM ignored for 32 s: every new id declared two publishers and two
liveliness tokens in the compass's loop. Now the devices with topics are bounded, new ones are declared within a
time budget per drain, the devices that have topics are published first, and what is kept off ROS 2 is counted.
The ROS 2 sink here runs on a stand-in session (no network): what it declares and puts is recorded."""

from __future__ import annotations

import time

import numpy as np
import pytest

from magnet import wire
from magnet.compass import CompassCore
from services.common.ros2_options import Ros2Settings
from services.compass import ros2
from services.compass.ros2 import Ros2Compass
from services.compass.settings import CompassSettings


class Declared:
    def __init__(self, session: FakeSession, key: str) -> None:
        self.session, self.key = session, key
        session.declared.add(key)
        session.declarations += 1

    def __enter__(self) -> Declared:
        return self

    def __exit__(self, *_: object) -> None:
        self.undeclare()

    def undeclare(self) -> None:
        self.session.declared.discard(self.key)

    def put(self, payload: bytes, attachment: bytes | None = None) -> None:
        self.session.puts.append(self.key)


class FakeSession:
    def __init__(self) -> None:
        self.declared: set[str] = set()
        self.declarations = 0
        self.puts: list[str] = []
        self.info = self

    def zid(self) -> str:
        return "0123456789abcdef"

    def liveliness(self) -> FakeSession:
        return self

    def declare_token(self, key: str) -> Declared:
        return Declared(self, "token:" + key)

    def declare_publisher(self, key: str, encoding: object = None) -> Declared:
        return Declared(self, key)


def drain(devices: list[str]) -> wire.RawColumns:
    now = time.time_ns()
    t_ns = now - np.arange(2, 0, -1, dtype=np.int64) * 20_000_000
    batches = [wire.RawBatch(d, 0, "sim", t_ns, np.tile([20.0, 0, 40], (2, 1))) for d in devices]
    return wire.RawColumns.from_batches(batches)


def publish(sink: Ros2Compass, core: CompassCore, devices: list[str]) -> None:
    columns = drain(devices)
    sink.publish(columns, core.step(columns, time.time_ns()), core)


def mag_puts(session: FakeSession, device: str) -> int:
    return sum(1 for key in session.puts if f"/{device}/mag/" in key or key.endswith(f"{device}/mag"))


def test_a_flood_of_new_ids_is_bounded_and_the_real_device_is_published_first(monkeypatch) -> None:
    session, core = FakeSession(), CompassCore()
    sink = Ros2Compass(session, Ros2Settings(True), "compass", max_devices=8)  # type: ignore[arg-type]
    publish(sink, core, ["real"])
    key = next(iter(sink.devices["real"][0])).key
    monkeypatch.setattr(ros2, "DECLARE_BUDGET_S", 0.0)  # one new device's topics per drain, at most
    flood = [f"flood-{k}" for k in range(300)]
    before = len(session.puts)
    publish(sink, core, [*flood[:150], "real", *flood[150:]])
    assert session.puts[before : before + 2] == [key, sink.devices["real"][0][1].key]  # the real device first
    assert len(sink.devices) == 2 and core.drops.counts == {"ros2:declare-budget": 299}
    monkeypatch.setattr(ros2, "DECLARE_BUDGET_S", 10.0)
    publish(sink, core, [*flood, "real"])
    assert len(sink.devices) == 8 and "real" in sink.devices
    assert core.drops.counts["ros2:device-limit"] == 299 - 6  # 299 new ids, 6 free slots
    status = core.status("compass").to_dict()
    assert status["sinks"] == {"ros2_topics": 8, "ros2_topics_evicted": 0}
    assert session.declarations == 1 + 2 + 4 * 8  # node, diagnostics, 8 devices: never one per id of the flood
    sink.close()
    assert session.declared == set()


def test_a_silent_device_gives_its_slot_to_a_new_one_and_it_is_counted() -> None:
    session, core = FakeSession(), CompassCore()
    sink = Ros2Compass(session, Ros2Settings(True), "compass", max_devices=2)  # type: ignore[arg-type]
    assert sink.admit(["a", "b"], core, now_s=100.0) == [True, True]
    assert sink.admit(["c"], core, now_s=100.0 + ros2.IDLE_S - 1) == [False]  # nobody silent long enough
    assert sink.admit(["b"], core, now_s=100.0 + ros2.IDLE_S - 1) == [True]
    assert sink.admit(["c"], core, now_s=100.0 + ros2.IDLE_S + 1) == [True]  # a, silent IDLE_S, made room
    assert list(sink.devices) == ["b", "c"] and sink.evicted == 1
    assert core.status("x").to_dict()["sinks"] == {"ros2_topics": 2, "ros2_topics_evicted": 1}
    assert core.drops.counts == {"ros2:device-limit": 1}
    sink.close()


def test_the_bound_is_an_option() -> None:
    assert CompassSettings().ros2_max_devices == 256
    with pytest.raises(ValueError, match="--ros2-max-devices"):
        CompassSettings(ros2_max_devices=0)
