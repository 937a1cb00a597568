"""Issue 32, memory per device in an edge: Zenoh 1.10.2 keeps about 1.1 kB for every liveliness token key a session
ever declared, undeclared or not, until the session closes (docs/front-door.md "Memory per service"). The MAVLink edge
declares two tokens for each device that appears while it runs and withdraws them when it falls silent: a port
flooded with new (system id, id) pairs each time (65,280 are possible) left every pair's keys behind. Behind a router
the edge now declares those tokens on a session of its own, renewed after ``TOKENS_PER_SESSION`` of them, the tokens
alive declared again on the new session before the old one closes. No network: stand-in sessions."""

from __future__ import annotations

import pytest
from test_edge_device_limit import FakeSession, FakeToken

from services.edge import service
from services.edge.service import EdgeStatus
from services.edge.settings import EdgeSettings


class OwnSession(FakeSession):
    """Every token key ever declared on it (what Zenoh keeps), and whether it is open."""

    def __init__(self) -> None:
        super().__init__()
        self.ever: set[str] = set()
        self.open = True

    def __enter__(self) -> OwnSession:
        return self

    def __exit__(self, *_: object) -> None:
        self.open = False

    def declare_token(self, key: str) -> FakeToken:
        self.ever.add(key)
        return super().declare_token(key)


def test_the_token_keys_a_session_declared_are_bounded_however_many_devices_came(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    monkeypatch.setattr(service, "TOKENS_PER_SESSION", 50)
    sessions: list[OwnSession] = []

    def opener() -> OwnSession:
        sessions.append(OwnSession())
        return sessions[-1]

    status = EdgeStatus(EdgeSettings(mavlink="udpin:127.0.0.1:14550", max_devices=64, device="e1"))
    status.open(FakeSession(), opener)  # type: ignore[arg-type]
    status.device_seen("mav1-mag1")  # a real vehicle, there throughout
    for flood in range(10):  # 30 new pairs a flood, unhealthy too, then silent and forgotten
        ids = [f"mav{100 + flood}-mag{k}" for k in range(30)]
        for device in ids:
            status.device_seen(device)
            status.device_health(device, False)
        for device in ids:
            status.device_gone(device)
    live = sessions[-1]
    # the new tokens of a session, and those alive when it opened (at most the vehicle's and a flood's 60)
    assert len(live.ever) <= service.TOKENS_PER_SESSION + 61  # before: the 601 keys of every pair, on one session
    assert status.renewed == len(sessions) - 1 >= 5
    assert all(not s.open and not s.tokens for s in sessions[:-1])
    assert live.tokens == ["magnet/@alive/device/mav1-mag1"]  # the vehicle's token on the new session
    status.close()
    assert not live.open and not live.tokens


def test_without_an_opener_the_tokens_stay_on_the_given_session() -> None:
    session = OwnSession()
    status = EdgeStatus(EdgeSettings(mavlink="udpin:127.0.0.1:14550", max_devices=4, device="e1"))
    status.open(session)  # type: ignore[arg-type]
    status.device_seen("mav1-mag1")
    assert session.tokens == ["magnet/@alive/device/mav1-mag1"] and status.renewed == 0
    status.close()
    assert session.open and not session.tokens
