"""A service's status, answered from Zenoh's thread (issue 32: status always answered within 1 s): the compass's and
the calibrator's.

Their loops answered the status between drains or chunks of samples: a drain of a flood of new ids, a garbage
collection in the middle of one, or a machine too busy to run the loop for a moment made the one answer wait (a soak
of 10 minutes: the compass 258 of 259 within 1 s, the missed one after a flood of 20,000 new ids; the calibrator 226
of 227). Now the loop writes its status (a fresh dict it never touches again) on this board, at most every
``refresh_s``, and the status queryable's callback answers every query at once, from Zenoh's thread, with the
board's latest: a status never waits for the loop. The answer says how old it is (``status_age_s``: how long ago
the loop wrote it; while the loop is in a long drain it grows, which is what an operator wants to see). The
service's state itself is only ever touched by the loop's thread.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import Any

import zenoh

from magnet import wire
from services.common.guard import Guard

#: the loop writes its status at most this often (s) unless the board is given another period: a fresh enough
#: answer, for a few hundred bytes packed 20 times a second
REFRESH_S = 0.05


class StatusBoard:
    """The latest status the loop wrote (``write``), answered to every query from Zenoh's thread (``answer``);
    ``refresh_s`` how often the loop writes it (None: ``REFRESH_S``)."""

    def __init__(
        self,
        key: str,
        guard: Guard,
        clock: Callable[[], float] = time.monotonic,
        refresh_s: float | None = None,
    ) -> None:
        self.key, self.guard, self.clock, self.refresh_s = key, guard, clock, refresh_s
        self.latest: tuple[dict[str, Any], float] | None = None  # (status, when written): replaced whole
        self.answered = 0

    def due(self) -> bool:
        """Whether the loop should write its status now (none yet, or the last one ``refresh_s`` old)."""
        latest = self.latest
        refresh_s = REFRESH_S if self.refresh_s is None else self.refresh_s
        return latest is None or self.clock() - latest[1] >= refresh_s

    def write(self, status: dict[str, Any]) -> None:
        """The loop's status now (from the loop's thread; ``status`` is not changed afterwards)."""
        self.latest = (status, self.clock())

    def read(self) -> dict[str, Any]:
        """The latest status with its age, as a query is answered (any thread; ``{}`` before the first write): what
        ``--metrics`` serves, so a scrape never touches the service's state from another thread than its loop's."""
        latest = self.latest
        if latest is None:
            return {}
        status, written_s = latest
        return {**status, "status_age_s": round(self.clock() - written_s, 3)}

    def answer(self, query: zenoh.Query) -> None:
        """The status queryable's callback (Zenoh's thread): the latest status, with its age; never raises."""
        self.guard.answer("query:status", query, self._reply)
        query.drop()  # finalize now: the asker waits for it

    def _reply(self, query: zenoh.Query) -> None:
        status = self.read()
        if not status:
            raise ValueError(f"the {self.guard.service} is starting: ask again in a moment")
        self.answered += 1
        query.reply(self.key, wire.pack(status))
