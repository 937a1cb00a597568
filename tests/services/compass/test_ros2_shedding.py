"""Issue 32: ``magnet compass --ros2`` hit with 12,000 new ids in 6 s left its status unanswered for 3.5 minutes, a
real device's ROS 2 output 237 s late and SIGTERM ignored for 32 s: every new id declared two publishers and two
liveliness tokens in the compass's loop. Now a device is given topics only once it has sent a few batches (a flood's
ids send one: Zenoh 1.10.2 keeps every declaration for good, so each one declared is memory), the devices with topics
are bounded, new ones are declared within a time budget per drain, the devices that have topics are published first,
and what is kept off ROS 2 is counted.
The ROS 2 sink here runs on a stand-in session (no network): what it declares and puts is recorded."""

from __future__ import annotations

import gc
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


def prove(sink: Ros2Compass, core: CompassCore, devices: list[str]) -> None:
    """Each of ``devices`` sends ``PROMOTE_BATCHES - 1`` batches, one a drain: counted, not yet given topics."""
    for _ in range(ros2.PROMOTE_BATCHES - 1):
        publish(sink, core, devices)


def test_a_flood_of_new_ids_is_bounded_and_the_real_device_is_published_first(monkeypatch) -> None:
    # a flood of ids that each send enough batches to be given topics (one that sends one batch: the test below),
    # every one of them counted until then (room for 300 ids counted with 8 slots)
    monkeypatch.setattr(ros2, "CANDIDATES_PER_SLOT", 40)
    session, core = FakeSession(), CompassCore()
    sink = Ros2Compass(session, Ros2Settings(True), "compass", max_devices=8)  # type: ignore[arg-type]
    prove(sink, core, ["real"])
    publish(sink, core, ["real"])
    key = next(iter(sink.devices["real"][0])).key
    flood = [f"flood-{k}" for k in range(300)]
    prove(sink, core, flood)
    assert session.declarations == 1 + 2 + 2 * 2 and len(sink.devices) == 1  # node, diagnostics, real
    unproven = (ros2.PROMOTE_BATCHES - 1) * 301
    assert core.drops.counts == {"ros2:unproven": unproven}
    monkeypatch.setattr(ros2, "DECLARE_BUDGET_S", 0.0)  # one new device's topics per drain, at most
    before = len(session.puts)
    publish(sink, core, [*flood[:150], "real", *flood[150:]])
    assert session.puts[before : before + 2] == [key, sink.devices["real"][0][1].key]  # the real device first
    assert len(sink.devices) == 2 and core.drops.counts == {"ros2:unproven": unproven, "ros2:declare-budget": 299}
    monkeypatch.setattr(ros2, "DECLARE_BUDGET_S", 10.0)
    publish(sink, core, [*flood, "real"])
    assert len(sink.devices) == 8 and "real" in sink.devices
    assert core.drops.counts["ros2:device-limit"] == 299 - 6  # 299 new ids, 6 free slots
    status = core.status("compass").to_dict()
    assert status["sinks"] == {"ros2_topics": 8, "ros2_topics_evicted": 0, "ros2_sessions_renewed": 0}
    assert session.declarations == 1 + 2 + 4 * 8  # node, diagnostics, 8 devices: never one per id of the flood
    sink.close()
    assert session.declared == set()


def test_ids_that_send_one_batch_declare_nothing_and_take_no_slot() -> None:
    """The soak's ROS 2 flood: 20,000 new ids, one batch each. Before, each took a slot once its holder was silent
    ``IDLE_S`` (256 devices' publishers and tokens declared and undeclared a flood, which Zenoh 1.10.2 keeps for good:
    the compass grew 4-8 MB a flood); now none is declared, and a real device starting during the flood gets a slot
    at once, every batch of its first drain published."""
    session, core = FakeSession(), CompassCore()
    sink = Ros2Compass(session, Ros2Settings(True), "compass", max_devices=2)  # type: ignore[arg-type]
    assert sink.admit(["old-a"] * 3 + ["old-b"] * 3, core, now_s=0.0) == [True] * 6
    flood = [f"flood-{k}" for k in range(5000)]
    batches = [*flood[:2500], *["real"] * ros2.PROMOTE_BATCHES, *flood[2500:]]
    admitted = sink.admit(batches, core, now_s=ros2.IDLE_S + 1)  # old-a and old-b silent: their slots may go
    assert [d for d, ok in zip(batches, admitted) if ok] == ["real"] * ros2.PROMOTE_BATCHES
    assert list(sink.devices) == ["old-b", "real"] and sink.evicted == 1
    assert session.declarations == 1 + 2 + 4 * 3  # node, diagnostics, old-a, old-b, real
    assert core.drops.counts == {"ros2:unproven": 5000}
    assert len(sink.candidates) <= ros2.CANDIDATES_PER_SLOT * 2  # the ids counted are bounded
    # a device sending one batch a drain is given topics with its PROMOTE_BATCHES-th
    assert [sink.admit(["slow"], core, now_s=2 * ros2.IDLE_S + 2) for _ in range(3)] == [[False], [False], [True]]
    assert core.drops.counts["ros2:unproven"] == 5000 + ros2.PROMOTE_BATCHES - 1
    sink.close()
    assert session.declared == set()


def test_a_silent_device_gives_its_slot_to_a_new_one_and_it_is_counted() -> None:
    session, core = FakeSession(), CompassCore()
    sink = Ros2Compass(session, Ros2Settings(True), "compass", max_devices=2)  # type: ignore[arg-type]
    three = ros2.PROMOTE_BATCHES  # batches in one drain: enough for topics
    assert sink.admit(["a"] * three + ["b"] * three, core, now_s=100.0) == [True] * 2 * three
    assert sink.admit(["c"] * three, core, now_s=100.0 + ros2.IDLE_S - 1) == [False] * three  # nobody silent long
    assert sink.admit(["b"], core, now_s=100.0 + ros2.IDLE_S - 1) == [True]
    assert sink.admit(["c"], core, now_s=100.0 + ros2.IDLE_S + 1) == [True]  # a, silent IDLE_S, made room
    assert list(sink.devices) == ["b", "c"] and sink.evicted == 1
    assert core.status("x").to_dict()["sinks"] == {
        "ros2_topics": 2,
        "ros2_topics_evicted": 1,
        "ros2_sessions_renewed": 0,
    }
    assert core.drops.counts == {"ros2:device-limit": 1}
    sink.close()


def test_the_bound_is_an_option() -> None:
    assert CompassSettings().ros2_max_devices == 256
    with pytest.raises(ValueError, match="--ros2-max-devices"):
        CompassSettings(ros2_max_devices=0)


def test_publishing_some_batches_of_a_drain_leaves_no_garbage_for_the_cycle_collector() -> None:
    """The cut of a drain to its published batches was a closure calling itself: a reference cycle per drain, with
    the drain's masks, freed only by the cycle collector (which the compass runs rarely: 300 of them, several MB,
    piled up in a soak's floods). Now freed as soon as the drain is published."""
    session, core = FakeSession(), CompassCore()
    sink = Ros2Compass(session, Ros2Settings(True), "compass", max_devices=8)  # type: ignore[arg-type]
    sink.admit(["real"] * ros2.PROMOTE_BATCHES, core, now_s=time.monotonic())
    columns = drain(["real", "flood-1", "flood-2"])
    out = core.step(columns, time.time_ns())
    gc.collect()
    gc.disable()
    try:
        sink.publish(columns, out, core)  # "real" published, the two flood ids kept off: the drain cut
        assert len(session.puts) == 2 * 2 and gc.collect() == 0
    finally:
        gc.enable()
    sink.close()
