"""Time limits of the dashboard's HTTP connections (uvicorn's h11 protocol, bounded).

uvicorn closes a keep-alive connection idle after a response, but not one that never sends a request, and it waits
for a client that stops reading for ever: issue 32 found that event streams had no timeout for slow clients, and
here 260 connections that never sent a byte stayed open and made uvicorn answer 503 to every request (its
``limit_concurrency`` counts them). ``BoundedH11`` adds:

- a deadline for every request head: ``HEAD_TIMEOUT_S`` from the connection (or from the end of the last response)
  to a whole request head, however the bytes trickle in (slowloris), else the connection is closed;
- at most ``MAX_WAITING`` connections waiting for a head: a new one past it closes the oldest waiting one (one that
  has waited ``MIN_WAIT_S`` at least: a burst of connections sending their heads is not cut), so idle connections
  never fill ``limit_concurrency`` and a real request always gets in (one closed so whose request is there unread, a
  burst on a busy machine, is answered 503 first: its client is told, not dropped);
- a stall limit for writing: a client that takes nothing for ``STALL_S`` while the server has more to send (the
  transport's buffer above its high-water mark: an event stream or a large ``/api/fleet`` to a client that stopped
  reading) is cut off. Its event stream ends and frees its place (``app.MAX_STREAMS``).
"""

from __future__ import annotations

import asyncio
import os
import socket
from collections import OrderedDict
from typing import Any, ClassVar

from uvicorn.protocols.http.h11_impl import H11Protocol

HEAD_TIMEOUT_S = 10.0
STALL_S = 10.0
MAX_WAITING = 128
#: a waiting connection younger than this is not closed to admit a newer one (its head may be on its way)
MIN_WAIT_S = 1.0
#: what a connection closed to admit a newer one is told when its request is there unread (uvicorn's own 503 words)
REFUSAL = (
    b"HTTP/1.1 503 Service Unavailable\r\ncontent-type: text/plain; charset=utf-8\r\nconnection: close\r\n"
    b"content-length: 45\r\n\r\nService Unavailable: too many waiting clients"
)


def _bytes_waiting(transport: asyncio.BaseTransport) -> bool:
    """Whether the client sent bytes the server has not read yet (peeked: nothing is taken)."""
    sock = transport.get_extra_info("socket")
    if sock is None:
        return False
    try:
        with socket.socket(fileno=os.dup(sock.fileno())) as peek:
            peek.setblocking(False)
            return bool(peek.recv(1, socket.MSG_PEEK))
    except OSError:  # nothing there (BlockingIOError), or the client is gone
        return False


class BoundedH11(H11Protocol):
    """uvicorn's ``H11Protocol`` with a head deadline, a bound on connections waiting for a head, and a write-stall
    limit (see the module). Give it as ``uvicorn.Config(http=BoundedH11)``."""

    #: connections waiting for a request head, oldest first (one server per process)
    waiting: ClassVar[OrderedDict[int, BoundedH11]] = OrderedDict()
    closed_idle = 0  # connections closed for a late head or to admit a newer one
    refused_waiting = 0  # of those, closed for a newer one with their request unread: answered REFUSAL
    cut_stalled = 0  # connections cut off for not reading
    gate: Any = None  # the ``gate.Gate`` that admitted this connection, told when it closes (None: no gate)

    @classmethod
    def make_room(cls, wanted: int) -> int:
        """Close up to ``wanted`` of the oldest connections waiting for a head that have waited ``MIN_WAIT_S``
        (those with a request unread answered ``REFUSAL``), as a new connection past ``MAX_WAITING`` does; how many
        were closed. ``gate.Gate`` calls it before refusing a connection at its limit."""
        closed = 0
        while closed < wanted and cls.waiting:
            oldest = next(iter(cls.waiting.values()))
            if oldest.loop.time() - oldest._armed_s < MIN_WAIT_S:
                break
            oldest._close_idle(refuse=True)
            closed += 1
        return closed

    def _release(self) -> None:
        if self.gate is not None:
            self.gate.release(self)

    def connection_made(self, transport: asyncio.Transport) -> None:  # type: ignore[override]
        self._head_timer: asyncio.TimerHandle | None = None
        self._stall_timer: asyncio.TimerHandle | None = None
        super().connection_made(transport)
        self._arm()

    def _arm(self) -> None:
        self._disarm()
        self._head_timer = self.loop.call_later(HEAD_TIMEOUT_S, self._close_idle)
        self._armed_s = self.loop.time()
        waiting = BoundedH11.waiting
        waiting[id(self)] = self
        while len(waiting) > MAX_WAITING:
            oldest = next(iter(waiting.values()))
            if self._armed_s - oldest._armed_s < MIN_WAIT_S:
                break  # a burst of new connections whose heads are on their way: none of them is idle yet
            oldest._close_idle(refuse=True)

    def _disarm(self) -> None:
        if self._head_timer is not None:
            self._head_timer.cancel()
            self._head_timer = None
        BoundedH11.waiting.pop(id(self), None)

    def _between_requests(self) -> bool:
        return self.cycle is None or self.cycle.response_complete

    def _close_idle(self, refuse: bool = False) -> None:
        """Close a connection waiting for a head; when it is closed to admit a newer one (``refuse``) and its
        request has arrived but not been read yet (a burst on a busy machine), it is answered ``REFUSAL`` first:
        its client is told, as by uvicorn's own limit, instead of seeing the connection drop."""
        self._disarm()
        if not self.transport.is_closing() and self._between_requests():
            BoundedH11.closed_idle += 1
            if refuse and _bytes_waiting(self.transport):
                BoundedH11.refused_waiting += 1
                self.transport.write(REFUSAL)
            self.transport.close()
            self._release()

    def handle_events(self) -> None:
        super().handle_events()
        if not self._between_requests():
            self._disarm()  # a request's head arrived: the response is under way

    def on_response_complete(self) -> None:
        self._arm()  # before uvicorn takes a pipelined request (which disarms again)
        super().on_response_complete()
        if self.transport.is_closing():
            self._disarm()

    def pause_writing(self) -> None:
        super().pause_writing()
        if self._stall_timer is None:
            self._stall_timer = self.loop.call_later(STALL_S, self._cut_stalled)

    def resume_writing(self) -> None:
        super().resume_writing()
        if self._stall_timer is not None:
            self._stall_timer.cancel()
            self._stall_timer = None

    def _cut_stalled(self) -> None:
        self._stall_timer = None
        if not self.transport.is_closing():
            BoundedH11.cut_stalled += 1
            self._release()
            self.transport.abort()  # connection_lost follows: the response's sender is told it disconnected

    def connection_lost(self, exc: Any) -> None:
        self._release()
        self._disarm()
        if self._stall_timer is not None:
            self._stall_timer.cancel()
            self._stall_timer = None
        super().connection_lost(exc)
