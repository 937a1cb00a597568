"""The compass's status, answered from Zenoh's thread (issue 32: status always answered within 1 s).

The compass's loop answered its status between drains: a drain of a flood of new ids, a garbage collection in the
middle of one, or a machine too busy to run the loop for a moment made the one answer wait (a soak of 10 minutes:
258 of 259 within 1 s, the one missed after a flood of 20,000 new ids). Now the loop writes its status (packed) on
this board after each step, at most every ``REFRESH_S``, and the status queryable's callback answers every query
at once, from Zenoh's thread, with the board's latest: a status never waits for a drain. The answer says how old
it is (``status_age_s``: how long ago the loop wrote it; while the loop is in a long drain it grows, which is what
an operator wants to see). The core itself is only ever touched by the loop's thread.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from typing import Any

import zenoh

from magnet import wire
from services.common.guard import Guard

log = logging.getLogger("magnet.compass")

#: the loop writes its status at most this often (s): a fresh enough answer, for a few hundred bytes packed 20 times
#: a second
REFRESH_S = 0.05


class StatusBoard:
    """The latest status the loop wrote (``write``), answered to every query from Zenoh's thread (``answer``)."""

    def __init__(self, key: str, guard: Guard, clock: Callable[[], float] = time.monotonic) -> None:
        self.key, self.guard, self.clock = key, guard, clock
        self.latest: tuple[dict[str, Any], float] | None = None  # (status, when written): replaced whole
        self.answered = 0

    def due(self) -> bool:
        """Whether the loop should write its status now (none yet, or the last one ``REFRESH_S`` old)."""
        latest = self.latest
        return latest is None or self.clock() - latest[1] >= REFRESH_S

    def write(self, status: dict[str, Any]) -> None:
        """The loop's status now (from the loop's thread)."""
        self.latest = (status, self.clock())

    def answer(self, query: zenoh.Query) -> None:
        """The status queryable's callback (Zenoh's thread): the latest status, with its age; never raises."""
        self.guard.answer("query:status", query, self._reply)
        query.drop()  # finalize now: the asker waits for it

    def _reply(self, query: zenoh.Query) -> None:
        latest = self.latest
        if latest is None:
            raise ValueError("the compass is starting: ask again in a moment")
        status, written_s = latest
        self.answered += 1
        query.reply(self.key, wire.pack({**status, "status_age_s": round(self.clock() - written_s, 3)}))
