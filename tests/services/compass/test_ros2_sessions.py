"""Issue 32, the compass's memory under edges restarted with new ids: Zenoh 1.10.2 keeps about 2 kB for every key
expression a session ever declared, undeclared or not (a device's ROS 2 topics: two publishers and two tokens, about
9 kB), and gives it back only when the session closes (measured, docs/front-door.md "Memory per service"). So the
ROS 2 sink, given an ``opener``, declares on a session of its own and opens a new one once it has declared topics for
``DEVICES_PER_SESSION`` devices per slot: the keys a live session holds are bounded however many devices came and went.
No network: stand-in sessions record what is declared on them."""

from __future__ import annotations

from test_ros2_shedding import Declared, FakeSession, publish

from magnet.compass import CompassCore
from services.common.ros2_options import Ros2Settings
from services.compass import ros2
from services.compass.ros2 import Ros2Compass


class OwnSession(FakeSession):
    """A stand-in session that remembers every key ever declared on it (what Zenoh keeps) and whether it is open."""

    def __init__(self) -> None:
        super().__init__()
        self.ever: set[str] = set()
        self.open = True

    def __enter__(self) -> OwnSession:
        return self

    def __exit__(self, *_: object) -> None:
        self.open = False

    def declare_token(self, key: str) -> Declared:
        self.ever.add("token:" + key)
        return super().declare_token(key)

    def declare_publisher(self, key: str, encoding: object = None) -> Declared:
        self.ever.add(key)
        return super().declare_publisher(key, encoding)


def test_the_keys_a_session_keeps_are_bounded_however_many_devices_came(monkeypatch) -> None:
    sessions: list[OwnSession] = []

    def opener() -> OwnSession:
        sessions.append(OwnSession())
        return sessions[-1]

    monkeypatch.setattr(ros2, "DECLARE_BUDGET_S", 10.0)
    core, slots = CompassCore(), 8
    sink = Ros2Compass(FakeSession(), Ros2Settings(True), "compass", max_devices=slots, opener=opener)  # type: ignore[arg-type]
    clock = [0.0]
    monkeypatch.setattr(ros2.time, "monotonic", lambda: clock[0])
    for restart in range(25):  # an edge restarted with 4 new ids each time, the old ones silent since
        clock[0] += ros2.IDLE_S + 1
        ids = [f"s{restart}-{k}" for k in range(4)]
        for _ in range(ros2.PROMOTE_BATCHES):
            publish(sink, core, ids)
        assert set(ids) <= set(sink.devices)
    live = sessions[-1]
    keys_per_device = 4  # two publishers, two tokens
    bound = keys_per_device * ros2.DEVICES_PER_SESSION * slots + 3  # and the node's token, the diagnostics' topic
    assert len(live.ever) <= bound  # before: every one of the 100 devices' keys, 403, in the one session
    assert len(sessions) > 1 and all(not s.open and not s.declared for s in sessions[:-1])
    assert core.status("compass").sinks["ros2_sessions_renewed"] == len(sessions) - 1
    # the devices that had topics when a session was renewed have them on the new one and are published there
    keys = [topic.key for topics, _ in sink.devices.values() for topic in topics]
    assert len(sink.devices) == slots and all(key in live.declared for key in keys)
    before = len(live.puts)
    publish(sink, core, list(sink.devices))
    assert len(live.puts) > before
    sink.close()
    assert not live.open and not live.declared


def test_without_an_opener_the_given_session_is_kept() -> None:
    """A peer (no router) declares on the compass's own session, which is never closed by the sink."""
    session, core = OwnSession(), CompassCore()
    sink = Ros2Compass(session, Ros2Settings(True), "compass", max_devices=2)  # type: ignore[arg-type]
    for _ in range(ros2.PROMOTE_BATCHES):
        publish(sink, core, ["a"])
    assert sink.session is session and "a" in sink.devices
    sink.close()
    assert session.open and not session.declared
