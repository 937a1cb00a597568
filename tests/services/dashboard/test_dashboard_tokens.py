"""Issue 32, the dashboard's memory under floods of device ids: Zenoh 1.10.2 keeps about 0.9 kB in a session for
every liveliness token key its subscriber was ever told of (500 new tokens a round from another process: +0.45 MB a
round for good; the same keys again: flat; docs/front-door.md "Memory per service"), given back only when the session
closes. Behind a router the ingest now takes the devices' tokens on a session of its own, renewed after
``TOKENS_PER_SESSION`` samples: the token keys a live session was told of are bounded however many devices came.
No network: stand-in sessions hold the samples."""

from __future__ import annotations

from typing import Any

import pytest
import zenoh
from test_dashboard_trim import Channel, Session

from services.dashboard import ingest
from services.dashboard.state import FleetState

ALIVE = "magnet/@alive/device/*"
LIVE: dict[str, bool] = {}  # the tokens alive in the network now: what a new subscriber's history gives


class Token:
    def __init__(self, device: str, alive: bool) -> None:
        self.key_expr = f"magnet/@alive/device/{device}"
        self.kind = zenoh.SampleKind.PUT if alive else zenoh.SampleKind.DELETE


class OwnSession(Session):
    """A session of the tokens' own: every token sample it was given (what Zenoh keeps), open or closed."""

    def __init__(self) -> None:
        super().__init__()
        self.told: set[str] = set()
        self.open = True

    def __enter__(self) -> OwnSession:
        return self

    def __exit__(self, *_: object) -> None:
        self.open = False

    def declare_subscriber(self, key: str, handler: Any, **kwargs: Any) -> Channel:
        channel = super().declare_subscriber(key, handler, **kwargs)
        if kwargs.get("history"):
            channel.samples = [Token(device, True) for device in LIVE]  # type: ignore[misc]
        return channel

    def tell(self, token: Token) -> None:
        self.told.add(str(token.key_expr))
        self.channels[ALIVE].samples.append(token)  # type: ignore[arg-type]


def test_the_token_keys_a_session_was_told_of_are_bounded(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(ingest, "TOKENS_PER_SESSION", 100)
    LIVE.clear()
    sessions: list[OwnSession] = []

    def opener() -> OwnSession:
        sessions.append(OwnSession())
        return sessions[-1]

    state = FleetState()
    with ingest.Ingest(Session(), "magnet", state, opener=opener) as feed:  # type: ignore[arg-type]
        LIVE["real"] = True
        sessions[-1].tell(Token("real", True))
        for flood in range(10):  # floods of 60 new ids: each token put, then withdrawn
            ids = [f"f{flood}-{k}" for k in range(60)]
            for device in ids:
                sessions[-1].tell(Token(device, True))
            feed.step()
            for device in ids:
                sessions[-1].tell(Token(device, False))
            feed.step()
        live = sessions[-1]
        assert len(live.told) <= 2 * ingest.TOKENS_PER_SESSION  # before: all 601 keys on the one session
        assert feed.renewed == len(sessions) - 1 >= 4
        assert all(not s.open for s in sessions[:-1]) and live.open
        assert state.rows["real"].alive is True  # given again by each new session's history
        assert not any(row.alive for device, row in state.rows.items() if device != "real")
    assert not live.open


def test_without_an_opener_the_tokens_stay_on_the_given_session() -> None:
    session = OwnSession()
    with ingest.Ingest(session, "magnet", FleetState()) as feed:  # type: ignore[arg-type]
        for k in range(ingest.TOKENS_PER_SESSION + 1):
            session.tell(Token(f"d{k}", True))
        feed.step()
        assert feed.renewed == 0 and session.open


def test_more_tokens_alive_than_a_session_takes_do_not_renew_it_at_every_step(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(ingest, "TOKENS_PER_SESSION", 10)
    LIVE.clear()
    LIVE.update(dict.fromkeys((f"d{k}" for k in range(50)), True))  # each new session's history: 50 tokens
    sessions: list[OwnSession] = []

    def opener() -> OwnSession:
        sessions.append(OwnSession())
        return sessions[-1]

    with ingest.Ingest(Session(), "magnet", FleetState(), opener=opener) as feed:  # type: ignore[arg-type]
        for _ in range(5):
            feed.step()
        assert feed.renewed == 0 and len(sessions) == 1
    LIVE.clear()
