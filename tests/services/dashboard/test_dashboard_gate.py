"""The dashboard's limit of connections at accept (``services.dashboard.gate``; issue 32's soak: a burst of 2,000
event streams made uvicorn's whole HTTP machinery for every connection before its limit answered 503, and the
arenas Python took for them stayed). No sockets here: the gate's count, its refusal and the room it makes."""

from __future__ import annotations

import asyncio
from typing import Any, ClassVar

from services.dashboard.gate import REFUSAL_503, Gate, Refusal


class Made:
    """Stands for ``BoundedH11``: made with uvicorn's keyword arguments; ``make_room`` closes idle ones."""

    idle: ClassVar[list[Made]] = []

    def __init__(self, **kwargs: Any) -> None:
        self.kwargs, self.gate = kwargs, None

    @classmethod
    def make_room(cls, wanted: int) -> int:
        closed = cls.idle[:wanted]
        del cls.idle[:wanted]
        for made in closed:
            made.gate.release(made)
        return len(closed)


def test_connections_past_the_limit_are_refused_without_a_protocol_and_admitted_again_once_one_closes():
    gate = Gate(Made, limit=3)
    admitted = [gate(config="c", server_state="s", app_state={}, _loop=None) for _ in range(3)]
    assert all(isinstance(made, Made) and made.gate is gate for made in admitted)
    assert admitted[0].kwargs == {"config": "c", "server_state": "s", "app_state": {}, "_loop": None}
    refused = [gate(config="c", server_state="s", app_state={}, _loop=None) for _ in range(5)]
    assert all(isinstance(r, Refusal) for r in refused) and (gate.made, gate.refused, gate.most) == (3, 5, 3)
    gate.release(admitted[1])  # closed or lost: its place is free (kept alive here: the loop holds it a while)
    assert isinstance(gate(config="c", server_state="s", app_state={}, _loop=None), Made) and gate.made == 4


def test_idle_connections_make_room_before_a_connection_is_refused():
    gate = Gate(Made, limit=2)
    first = [gate(config=None, server_state=None, app_state=None, _loop=None) for _ in range(2)]
    Made.idle = [first[0]]  # one has waited for its head long enough to be closed for a newer one
    third = gate(config=None, server_state=None, app_state=None, _loop=None)
    assert isinstance(third, Made)
    assert isinstance(gate(config=None, server_state=None, app_state=None, _loop=None), Refusal)  # none idle now
    del first, third  # a protocol the loop dropped without connecting it (no connection_lost) frees its place too
    assert isinstance(gate(config=None, server_state=None, app_state=None, _loop=None), Made)


class Transport(asyncio.Transport):
    def __init__(self) -> None:
        super().__init__()
        self.written, self.closed = b"", False

    def write(self, data: bytes) -> None:  # type: ignore[override]
        self.written += data

    def close(self) -> None:
        self.closed = True


def test_a_refused_connection_is_answered_503_and_closed_once_its_request_head_is_read():
    async def main() -> None:
        refusal, transport = Refusal(), Transport()
        refusal.connection_made(transport)
        assert transport.written == REFUSAL_503 and not transport.closed  # told at once, its request not yet read
        head, body = REFUSAL_503.split(b"\r\n\r\n")
        assert head.startswith(b"HTTP/1.1 503 ") and f"content-length: {len(body)}".encode() in head
        refusal.data_received(b"GET /api/stream HTTP/1.1\r\nHost: x\r")
        assert not transport.closed
        refusal.data_received(b"\n\r\n")  # the end of the head, across reads
        assert transport.closed
        refusal.connection_lost(None)
        silent, quiet = Refusal(), Transport()
        silent.connection_made(quiet)
        assert silent.timer is not None and not quiet.closed  # a client that sends nothing: closed by the timer
        silent.connection_lost(None)
        assert silent.timer is None

    asyncio.run(main())
