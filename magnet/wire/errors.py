"""Errors of the wire format and the counter services drop malformed messages by."""

from __future__ import annotations

import logging


class WireError(ValueError):
    """A message that cannot be used. ``cause`` is a short token to count drops by (``DropCounter``)."""

    def __init__(self, cause: str, message: str) -> None:
        super().__init__(message)
        self.cause = cause


#: causes of a message that is well formed but not applied, and the word its log line uses (any other cause: malformed)
NOT_MALFORMED = {"stale": "stale", "not-accepted": "not-accepted"}


class DropCounter:
    """Counts dropped messages by cause. ``count`` returns True the first time a cause is seen (log it then)."""

    def __init__(self) -> None:
        self.counts: dict[str, int] = {}

    def count(self, cause: str, n: int = 1) -> bool:
        """Count ``n`` drops of ``cause``; True when it is the first time this cause is seen."""
        first = cause not in self.counts
        self.counts[cause] = self.counts.get(cause, 0) + n
        return first

    def drop(self, exc: WireError, what: str, logger: logging.Logger) -> None:
        """Count a dropped ``what`` message (``<what>:<cause>``); log only the first of each cause."""
        if self.count(f"{what}:{exc.cause}"):
            word = NOT_MALFORMED.get(exc.cause, "malformed")
            logger.warning("dropping %s %s message (%s): %s; further ones only counted", word, what, exc.cause, exc)

    @property
    def total(self) -> int:
        return sum(self.counts.values())
