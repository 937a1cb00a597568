"""The fleet events of the dashboard's event streams: made once a tick for all of them, off the event loop.

Each stream used to ask the state for the rows changed since its own last event and encode them, every refresh:
the cost grew with the number of streams times the rows changing (issue 32: 2,000 streams took 73 % of a core).
Then the streams shared one event a tick, but made it themselves, on the event loop, whichever woke first: with
10,000 rows a page's first event (every row, 6 MB) took longer than a tick to make on a loaded machine, so every
new stream found it out of date and made it again, each one blocking the loop for as long (measured in a 5-minute
soak: the loop stuck in those encodings for minutes, 5,879 of 8,000 streams answered neither 200 nor 503, and the
dashboard at 781 MB from the 6 MB copies each slow stream held while it sent its own).

Now one producer makes the events (``make``, in a worker thread, ``run``), and a stream only looks up what to send
(``take``): it never encodes, so the loop stays free to accept, refuse and serve whatever the fleet does. Each tick
``make`` encodes the rows changed since the previous tick (a link of the ``chain``, from one version to the next);
the chain keeps the last ``KEPT_TICKS`` links within ``KEPT_BYTES``. Every row (``full``) is made only when a stream
asks for it (a new one, or one further behind than the chain) and the one made before has left the chain, so a
burst of new streams costs one encoding, not one each. A stream is sent the links after its version (at most the chain:
``KEPT_BYTES``), or, when it is further behind than the chain, every row again (``full: true``: a counted ``resync``,
its backlog dropped). A stream that needed ``RESYNCS_TO_CLOSE`` resyncs in a row cannot keep
up: it is closed with an ``event: closed`` saying why (``closed`` counted), not left to hold events in memory.

Events are UTF-8 bytes, encoded once: every stream sends the same object, in pieces of ``PIECE_BYTES`` (each after
its transport drained), so a stream whose client reads slowly holds one piece in its transport and at most one
chain's or one full event's worth of references. Rows are encoded ``CHUNK_ROWS`` at a time so the worker thread lets
the loop run between chunks (one ``json.dumps`` of 10,000 rows holds the GIL throughout).
"""

from __future__ import annotations

import asyncio
import concurrent.futures
import dataclasses
import io
import json
import threading
from typing import Any

from services.dashboard.state import FleetState

#: ticks' events kept for streams that woke late (a chain of links from one version to the next)
KEPT_TICKS = 16
#: the chain is also kept within this many bytes (a flood changing every row each tick makes links of MBs)
KEPT_BYTES = 16 * 1024 * 1024
#: a stream writes an event in pieces of at most this many bytes, each after its transport drained
PIECE_BYTES = 64 * 1024
#: rows encoded by one ``json.dumps`` (the producer thread gives the GIL up between chunks)
CHUNK_ROWS = 200
#: a stream sent every row again this many times in a row cannot keep up: it is closed, saying so
RESYNCS_TO_CLOSE = 3


def encode(name: str, data: Any) -> str:
    """One server-sent event."""
    return f"event: {name}\ndata: {json.dumps(data, separators=(',', ':'), allow_nan=False)}\n\n"


def _dumps(data: Any) -> str:
    return json.dumps(data, separators=(",", ":"), allow_nan=False)


def _rows_json(rows: list[dict[str, Any]]) -> bytes:
    return _dumps(rows)[1:-1].encode()


EVENT_HEAD = b"event: fleet\ndata: "


def encode_fleet(fleet: dict[str, Any], summary: dict[str, Any]) -> bytes:
    """The ``fleet`` event of ``FleetState.fleet``'s answer and its ``summary``, as UTF-8 bytes."""
    rows, out = fleet["rows"], _Out(EVENT_HEAD)
    for i in range(0, len(rows), CHUNK_ROWS):
        out.rows(rows[i : i + CHUNK_ROWS])
    return out.close({k: v for k, v in fleet.items() if k != "rows"}, summary, b"\n\n")


class _Out:
    """An event or body written as its rows are encoded, into one buffer that becomes the result without a copy
    (``BytesIO.getvalue`` hands its own buffer over): making every row of 10,000 (5.3 MB) peaks at its size and a
    chunk's, not at the chunks, their join and two more copies for the head and tail (+16 MB, issue 32's bursts)."""

    def __init__(self, head: bytes) -> None:
        self.buffer = io.BytesIO()
        self.buffer.write(head + b'{"rows":[')
        self.first = True

    def rows(self, rows: list[dict[str, Any]]) -> None:
        if not self.first:
            self.buffer.write(b",")
        self.buffer.write(_rows_json(rows))
        self.first = False

    def close(self, rest: dict[str, Any], summary: dict[str, Any], tail: bytes) -> bytes:
        self.buffer.write(b"]," + _dumps(rest | {"summary": summary})[1:].encode() + tail)
        text = self.buffer.getvalue()
        self.buffer = io.BytesIO()
        return text


def _made(state: FleetState, since: int, head: bytes, tail: bytes) -> tuple[int, bytes]:
    out = _Out(head)
    rest, _ = state.fleet_chunks(since, out.rows, CHUNK_ROWS)
    return rest["version"], out.close(rest, state.summary(), tail)


def fleet_event(state: FleetState, since: int) -> tuple[int, bytes]:
    """(the version, the ``fleet`` event) bringing a page from ``since`` (-1: every row): the rows encoded
    ``CHUNK_ROWS`` at a time as the state makes them and written at once into the event (the same JSON as
    ``encode_fleet`` of ``state.fleet``; the worker gives the GIL up between chunks, and never holds every row's map,
    nor the rows' JSON twice)."""
    return _made(state, since, EVENT_HEAD, b"\n\n")


def fleet_body(state: FleetState) -> bytes:
    """``/api/fleet``'s JSON body (every row and the summary), made as ``fleet_event``."""
    return _made(state, -1, b"", b"")[1]


@dataclasses.dataclass(frozen=True)
class Link:
    """A tick's event: the rows changed from version ``base`` to ``version``, encoded."""

    base: int
    version: int
    text: bytes


@dataclasses.dataclass
class Reader:
    """What one stream has had: the version its page is up to (-1: nothing yet), resyncs in a row."""

    version: int = -1
    resyncs: int = 0


class FleetEvents:
    """The ticks' fleet events, shared. ``make`` runs in the producer's thread (``run``); ``take`` on the loop."""

    def __init__(self, state: FleetState, interval_s: float) -> None:
        self.state, self.interval_s = state, interval_s
        self.lock = threading.Lock()  # swaps of ``chain`` and ``full`` (made in the worker, read on the loop)
        self.chain: tuple[Link, ...] = ()
        self.version = -1  # the version the newest link brings a page to
        self.full: tuple[int, bytes] | None = None  # every row: (its version, the event)
        self.wants_full = False  # a stream waits for every row
        self.made = 0  # events encoded: what the streams cost
        self.resyncs = 0  # streams sent every row again (further behind than the chain)
        self.closed = 0  # streams closed for not keeping up
        self.ticked = asyncio.Event()  # set after each tick's making (a new one each tick)
        self.readers = 0  # streams reading now (counted by the app): the producer runs while there are any
        self.producer: asyncio.Task[None] | None = None
        self.executor: concurrent.futures.ThreadPoolExecutor | None = None

    # ---------------------------------------------------------------------------------------------- making
    def wait_s(self, now_s: float) -> float:
        """Seconds from ``now_s`` to just past the next tick."""
        return self.interval_s - now_s % self.interval_s + 0.002

    def make(self) -> None:
        """One tick: the link of the rows changed since the last one, and every row when a stream wants them and
        the last ``full`` has left the chain (or there is none). The first tick after a start (no chain) makes every
        row only, and a chain from its version: a new stream needs nothing else."""
        if not self.chain:
            version, text = fleet_event(self.state, -1)
            self.made += 1
            with self.lock:  # an empty link: the chain starts at this version (sent to nobody)
                self.chain, self.version = (Link(version, version, b""),), version
                self.full, self.wants_full = (version, text), False
            return
        link = Link(self.version, *fleet_event(self.state, self.version))
        self.made += 1
        with self.lock:
            kept = [*self.chain, link][-KEPT_TICKS:]
            while len(kept) > 1 and sum(len(k.text) for k in kept) > KEPT_BYTES:
                kept.pop(0)
            self.chain, self.version = tuple(kept), link.version
            if self.full is not None and self.full[0] < self.chain[0].base:
                self.full = None  # out of the chain: no stream could be brought on from it
            wanted, self.wants_full = self.wants_full, False
        if wanted and self.full is None:
            version, text = fleet_event(self.state, -1)
            self.made += 1
            with self.lock:
                if version >= self.chain[0].base:
                    self.full = (version, text)

    async def run(self, stopping: asyncio.Event) -> None:
        """Make the events every tick while streams read them (``readers``), in a thread of its own; the loop only
        waits for it."""
        loop = asyncio.get_running_loop()
        if self.executor is None:
            self.executor = concurrent.futures.ThreadPoolExecutor(1, thread_name_prefix="dashboard-events")
        try:
            while not stopping.is_set() and self.readers:
                await loop.run_in_executor(self.executor, self.make)
                ticked, self.ticked = self.ticked, asyncio.Event()
                ticked.set()
                await asyncio.sleep(self.wait_s(loop.time()))
        finally:
            if (
                not self.readers
            ):  # nobody reads: the events kept go (a flood's links are MBs); a new stream waits a tick
                with self.lock:
                    self.chain, self.full = (), None
            self.ticked.set()

    def start(self, stopping: asyncio.Event) -> None:
        """The producer, unless it runs already (call from the loop, a stream having been counted in ``readers``)."""
        if self.producer is None or self.producer.done():
            self.producer = asyncio.get_running_loop().create_task(self.run(stopping))

    def close(self) -> None:
        if self.executor is not None:
            self.executor.shutdown(wait=False)
            self.executor = None

    # ---------------------------------------------------------------------------------------------- taking
    def take(self, reader: Reader) -> tuple[list[bytes], str | None]:
        """(the events to send ``reader`` now, oldest first, and None; or no events and the reason to close it);
        ``reader.version`` becomes the version they bring its page to. Looks up only: nothing is encoded here."""
        with self.lock:
            chain, full = self.chain, self.full
        if reader.version >= 0 and not (chain and chain[0].base <= reader.version):
            # further behind than the chain: its backlog is dropped, and it is sent every row again as a new one
            self.resyncs += 1
            reader.resyncs += 1
            if reader.resyncs >= RESYNCS_TO_CLOSE:
                self.closed += 1
                return [], (
                    f"this stream fell behind the fleet's last {KEPT_TICKS} events {RESYNCS_TO_CLOSE} times in a row "
                    "(its connection reads too slowly): closed; the page connects again"
                )
            reader.version = -1
        if reader.version >= 0:
            links = [link.text for link in chain if link.version > reader.version]
            if links:
                reader.version, reader.resyncs = chain[-1].version, 0
            return links, None
        if full is None:  # new (or resynced): every row, made at the next tick
            self.wants_full = True
            return [], None
        version, text = full
        reader.version = max([version, *(link.version for link in chain)])
        return [text] + [link.text for link in chain if link.version > version], None


def pieces(event: bytes) -> list[memoryview]:
    """``event`` in views of at most ``PIECE_BYTES`` (no copy)."""
    view = memoryview(event)
    return [view[start : start + PIECE_BYTES] for start in range(0, len(event), PIECE_BYTES)]
