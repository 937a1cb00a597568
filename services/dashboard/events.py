"""The fleet events of the dashboard's event streams, made once a tick for all of them.

Each stream used to ask the state for the rows changed since its own last event and encode them, every refresh:
the cost grew with the number of streams times the rows changing (issue 32: 2,000 streams took 73 % of a core).
Now streams wake on a common tick (``interval_s`` boundaries of the loop's clock) and the first to wake makes the
tick's event: the rows changed since the previous tick's, encoded once, sent as they are to every stream that had
the previous one. The last ``KEPT_TICKS`` ticks' events are kept: a stream woken late by a busy loop is sent the
ticks it missed as they were made. A new stream gets every row (made at most once a tick for all new ones), one
further behind an event of its own (the rows changed since its version); either is then counted as up to the tick's
version: rows changed in between are sent again with the next tick (a row sent twice is the same row), none is
missed, and from the next tick it shares the common events.

Events are UTF-8 bytes, encoded once: every stream sends the same object (a stream sends it in pieces of
``PIECE_BYTES``, so that a stream whose client reads slowly holds one piece in its transport, not a copy of a fleet
of 10,000 rows: 64 streams of a 4 MB event took 250 MB at once).
"""

from __future__ import annotations

import json
from collections import deque
from typing import Any

from services.dashboard.state import FleetState

#: ticks' events kept for streams that woke late
KEPT_TICKS = 16
#: a stream writes an event in pieces of at most this many bytes, each after its transport drained
PIECE_BYTES = 64 * 1024


def encode(name: str, data: Any) -> str:
    """One server-sent event."""
    return f"event: {name}\ndata: {json.dumps(data, separators=(',', ':'), allow_nan=False)}\n\n"


class FleetEvents:
    """The ticks' fleet events, shared (``event``); one per dashboard, used from its event loop only."""

    def __init__(self, state: FleetState, interval_s: float) -> None:
        self.state, self.interval_s = state, interval_s
        self.tick, self.version = -1, -1
        #: the last ticks' events: (the version each brings a page from, to, its text)
        self.recent: deque[tuple[int, int, bytes]] = deque(maxlen=KEPT_TICKS)
        self.full_tick, self.full_text = -1, b""  # every row, made at most once a tick for new streams
        self.made = 0  # events encoded (shared and own): what the streams cost

    def wait_s(self, now_s: float) -> float:
        """Seconds from ``now_s`` to just past the next tick."""
        return self.interval_s - now_s % self.interval_s + 0.002

    def event(self, since: int, now_s: float) -> tuple[int, list[bytes]]:
        """(the version the stream is now up to, the fleet events to send it: none when it had this tick's) for a
        stream last up to ``since`` (-1: a new stream)."""
        tick = int(now_s // self.interval_s)
        if tick != self.tick:
            fleet = self.state.fleet(self.version)
            self.recent.append((self.version, fleet["version"], self._encode(fleet)))
            self.tick, self.version = tick, fleet["version"]
        if since == self.version and since >= 0:
            return since, []  # woke twice in one tick
        if since < 0:
            if self.full_tick != tick:
                self.full_tick, self.full_text = tick, self._encode(self.state.fleet(-1))
            return self.version, [self.full_text]
        for i, (base, _, _) in enumerate(self.recent):
            if base == since:  # the ticks it missed (a busy loop wakes streams late), already made
                return self.version, [text for _, _, text in list(self.recent)[i:]]
        own = self.state.fleet(since)  # further behind than the ticks kept
        return min(own["version"], self.version), [self._encode(own)]

    def _encode(self, fleet: dict[str, Any]) -> bytes:
        self.made += 1
        return encode("fleet", fleet | {"summary": self.state.summary()}).encode()


def pieces(event: bytes) -> list[memoryview]:
    """``event`` in views of at most ``PIECE_BYTES`` (no copy)."""
    view = memoryview(event)
    return [view[start : start + PIECE_BYTES] for start in range(0, len(event), PIECE_BYTES)]
