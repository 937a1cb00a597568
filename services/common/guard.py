"""No handler ends a service: the one wrapper every subscriber, queryable and HTTP handler of ``services/`` runs in.

A handler that raises anything (a store that cannot be written, a message that fails to decode, a bug) is caught
here, once for every service: a query is answered with an error the asker can act on (``refusal``), a subscriber's
message is dropped and counted by cause (``<what>:handler-<ExceptionName>``, beside the wire's own drop causes in
the service's status) and one line is logged (the first of each cause, then every ``LOG_EVERY``-th), never a
traceback. The loop that called the handler goes on with the next message or query.

``KeyboardInterrupt`` and ``SystemExit`` are not caught (they are how a process is asked to end).
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from typing import Any, TypeVar

import zenoh

from magnet import wire

T = TypeVar("T")

#: after the first line of a cause, one more line for every LOG_EVERY failures of that cause
LOG_EVERY = 1000


def cause(what: str, exc: BaseException) -> str:
    """The drop cause a failure is counted by: ``<what>:handler-<ExceptionName>``."""
    return f"{what}:handler-{type(exc).__name__}"


def refusal(exc: BaseException, service: str) -> str:
    """The error a query gets for ``exc``: the exception's own words for what the asker or the operator can act on
    (a ValueError: bad parameters; an OSError: the store or the disk), else a bug, said as such."""
    text = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
    if isinstance(exc, (ValueError, OSError)):
        return text
    return f"the {service} failed to answer ({type(exc).__name__}: {text}); it logged it and keeps serving"


class Guard:
    """Runs handlers so that none ends the service: failures counted in ``drops`` (the service's drop counter,
    shown in its status) and logged one line at a time on ``log``."""

    def __init__(self, service: str, log: logging.Logger, drops: wire.DropCounter | None = None) -> None:
        self.service, self.log = service, log
        self.drops = drops if drops is not None else wire.DropCounter()

    def failed(self, what: str, exc: BaseException, count: int = 1) -> None:
        """Count ``count`` items of ``what`` lost to ``exc`` and log one line when due."""
        key = cause(what, exc)
        before = self.drops.counts.get(key, 0)
        self.drops.counts[key] = before + count
        if before == 0 or (before + count) // LOG_EVERY > before // LOG_EVERY:
            self.log.error(
                "%s handler failed (%s: %s); %d so far, counted in status dropped[%s]; the %s keeps running",
                what,
                type(exc).__name__,
                str(exc).strip().splitlines()[0] if str(exc).strip() else "",
                before + count,
                key,
                self.service,
            )

    def run(self, what: str, handler: Callable[..., T], *args: Any, count: int = 1) -> T | None:
        """``handler(*args)``; on any exception: counted as ``count`` dropped ``what`` items, logged, None."""
        try:
            return handler(*args)
        except Exception as exc:  # the point of this module: nothing a handler does ends the service
            self.failed(what, exc, count)
            return None

    def answer(self, what: str, query: zenoh.Query, handler: Callable[..., object], *args: Any) -> bool:
        """``handler(query, *args)`` for one query; on any exception the query gets ``reply_err`` with the
        ``refusal`` (counted and logged). False when it failed."""
        try:
            handler(query, *args)
            return True
        except Exception as exc:  # answered with an error, never raised into the service loop
            self.failed(what, exc)
            try:
                query.reply_err(refusal(exc, self.service).encode())
            except Exception as reply_exc:  # the asker is gone or the query was answered already
                self.log.debug("could not send the error reply: %s", reply_exc)
            return False
