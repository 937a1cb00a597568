"""The dashboard's limit of connections, kept where a connection is accepted (issue 32's soak).

uvicorn's ``limit_concurrency`` is judged when a request has been read: every connection of a burst first gets
uvicorn's whole HTTP machinery (its protocol, an h11 state machine, a request cycle, a task running the 503 app and
a log record), all of it made at once when 2,000 event streams connect together. Measured in a reproduction of the
soak's burst, the dashboard's live Python objects went 21 -> 30.5 MB during a burst and pymalloc's arenas 22 -> 34
after the first one, kept for the life of the process: a burst that comes when the others' freed pools are
pinned takes new arenas, so the dashboard's level after a burst depended on which burst it was.

``Gate`` is the protocol factory uvicorn is given (``uvicorn.Config(http=Gate(BoundedH11, limit))``): it counts the
connections it admitted that are neither lost nor being closed, and past ``limit`` it first lets
``BoundedH11.make_room`` close connections idle since ``MIN_WAIT_S`` (as a new connection always could), then
answers the rest with ``Refusal``: a fixed 503 written at once (uvicorn's words, ``Connection: close``), the request
read and dropped, the connection closed once its head has arrived (a close with the request unread would be a reset
on Linux) or after ``REFUSE_WAIT_S``. A refused connection costs the loop a transport and this small object, no
parsing and no task. uvicorn's own limit stays behind it (a connection admitted while tasks are at the limit).
"""

from __future__ import annotations

import asyncio
import logging
import time
import weakref
from typing import Any

log = logging.getLogger("magnet.dashboard")

#: a refused connection whose request head has not arrived by then is closed anyway (a client that sends nothing)
REFUSE_WAIT_S = 2.0
#: what a connection past the limit is answered (the words of uvicorn's own 503, so a client tells them apart from
#: the app's limit of event streams as before)
REFUSAL_503 = (
    b"HTTP/1.1 503 Service Unavailable\r\ncontent-type: text/plain; charset=utf-8\r\nconnection: close\r\n"
    b"content-length: 19\r\n\r\nService Unavailable"
)
#: a refused client's bytes read before closing anyway (a request head larger than this is not waited for)
REFUSE_READ_BYTES = 16384
#: refusals are logged once per this many seconds, with their count
LOG_EVERY_S = 10.0


class Refusal(asyncio.Protocol):
    """A connection refused at accept: ``REFUSAL_503`` at once, then closed when its request head has been read
    (or after ``REFUSE_WAIT_S``); nothing of the request is parsed."""

    __slots__ = ("read", "tail", "timer", "transport")

    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        assert isinstance(transport, asyncio.Transport)
        self.transport, self.tail, self.read = transport, b"", 0
        transport.write(REFUSAL_503)
        self.timer: asyncio.TimerHandle | None = asyncio.get_running_loop().call_later(REFUSE_WAIT_S, transport.close)

    def data_received(self, data: bytes) -> None:
        self.read += len(data)
        if b"\r\n\r\n" in self.tail + data or self.read > REFUSE_READ_BYTES:
            self.transport.close()  # the head read: a plain close (FIN) after the 503
        self.tail = data[-3:]

    def eof_received(self) -> bool:
        return False  # the client is done: close

    def connection_lost(self, exc: Exception | None) -> None:
        if self.timer is not None:
            self.timer.cancel()
            self.timer = None


class Gate:
    """uvicorn's protocol factory with the limit of connections at accept (see the module). ``protocol`` is made
    with uvicorn's arguments for an admitted connection; it tells the gate when it is closed or lost
    (``release``)."""

    def __init__(self, protocol: Any, limit: int, clock: Any = time.monotonic) -> None:
        self.protocol, self.limit, self.clock = protocol, limit, clock
        self.admitted: weakref.WeakSet[Any] = weakref.WeakSet()  # made, neither lost nor closing (or dropped)
        self.made = self.refused = 0  # connections admitted (a protocol made), refused at accept
        self.most = 0  # the most admitted at once
        self._logged_at, self._logged = -1e18, 0

    def __call__(self, **kwargs: Any) -> asyncio.Protocol:
        if len(self.admitted) >= self.limit:
            make_room = getattr(self.protocol, "make_room", None)
            if make_room is not None:
                make_room(len(self.admitted) - self.limit + 1)
        if len(self.admitted) >= self.limit:
            self._refused()
            return Refusal()
        made = self.protocol(**kwargs)
        made.gate = self
        self.made += 1
        self.admitted.add(made)
        self.most = max(self.most, len(self.admitted))
        return made

    def release(self, protocol: Any) -> None:
        self.admitted.discard(protocol)

    def _refused(self) -> None:
        self.refused += 1
        now = self.clock()
        if now - self._logged_at >= LOG_EVERY_S:
            log.warning("%d connections open: refused at accept (503), %d since the last line", self.limit,
                        self.refused - self._logged)  # fmt: skip
            self._logged_at, self._logged = now, self.refused
