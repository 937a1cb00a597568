"""The one loop that reads a sensor until it gives a usable sample: bounded backoff, counted errors, health.

``magnet edge`` and ``magnet sample`` both read through ``ReadLoop.next()``. A driver's ``read()`` retries a transfer a
few times (milliseconds) and then raises ``SensorReadError`` (an ``OSError``); this loop is the level above it:

- a failed read (any ``OSError``) is counted (``errors``, ``errors_by_cause``) and followed by a wait that doubles
  from ``Backoff.initial_s`` up to ``Backoff.max_s``, so a dead bus costs at most about one read attempt per
  ``max_s`` seconds instead of a busy spin;
- a reading with nothing new (``ready == False``) is polled again after ``Backoff.poll_s``; ``Backoff.max_polls``
  polls in a row without data count as one failure of cause ``stalled`` (a chip that stopped measuring);
- an overflowed reading is counted (``overflows``) and skipped;
- after ``Backoff.unhealthy_after`` consecutive failures the loop is unhealthy; the next usable reading makes it
  healthy again; each change is reported once through ``on_health(healthy, last_error)``;
- with ``Backoff.give_up_after`` set, that many consecutive failures raise ``SensorReadError`` (a one-shot command
  ends with a clear error); unset (the edge), the loop keeps trying until ``stop()`` is true.

Pure: the clock (seconds, monotonic) and the sleep are injected; nothing here touches threads, sockets or a bus.
"""

from __future__ import annotations

import dataclasses
import errno
import logging
from collections.abc import Callable
from typing import Any

from magnet.drivers.base import Reading, SensorReadError

log = logging.getLogger(__name__)

STALLED = "stalled"


@dataclasses.dataclass(frozen=True)
class Backoff:
    """How the loop waits. Seconds throughout; counts are consecutive events."""

    initial_s: float = 0.01
    factor: float = 2.0
    max_s: float = 1.0
    unhealthy_after: int = 3
    poll_s: float = 0.0005
    max_polls: int = 200
    give_up_after: int | None = None

    def __post_init__(self) -> None:
        if not 0 <= self.initial_s <= self.max_s:
            raise ValueError(f"backoff needs 0 <= initial_s <= max_s, got {self.initial_s} and {self.max_s}")
        if self.factor < 1:
            raise ValueError(f"backoff factor must be >= 1, got {self.factor}")
        if self.unhealthy_after < 1 or self.max_polls < 1 or self.poll_s < 0:
            raise ValueError("unhealthy_after and max_polls must be >= 1 and poll_s >= 0")
        if self.give_up_after is not None and self.give_up_after < 1:
            raise ValueError(f"give_up_after must be >= 1 or None, got {self.give_up_after}")

    def delay_s(self, consecutive_failures: int) -> float:
        """Wait after the ``consecutive_failures``-th failure in a row (1-based): initial * factor^(n-1), capped."""
        exponent = min(max(consecutive_failures - 1, 0), 64)
        return float(min(self.max_s, self.initial_s * self.factor**exponent))


@dataclasses.dataclass
class ReadStats:
    """Counters of one loop (mutable: the loop updates them; read them from anywhere for a status reply).

    attempts: calls of the sensor's ``read()``; samples: usable readings returned; errors: failed reads and stalls;
    not_ready: polls with nothing new; overflows: saturated readings skipped; waited_s: total backoff slept (s).
    """

    attempts: int = 0
    samples: int = 0
    errors: int = 0
    not_ready: int = 0
    overflows: int = 0
    consecutive_failures: int = 0
    healthy: bool = True
    last_error: str = ""
    waited_s: float = 0.0
    errors_by_cause: dict[str, int] = dataclasses.field(default_factory=dict)

    def as_dict(self) -> dict[str, Any]:
        out = dataclasses.asdict(self)
        out["waited_s"] = round(self.waited_s, 3)
        return out


def _cause(exc: OSError) -> str:
    code = exc.errno
    return errno.errorcode.get(code, f"errno {code}") if code else type(exc).__name__


class ReadLoop:
    """Reads ``read()`` (a driver's ``Sensor.read``) until a usable sample comes, per ``Backoff``.

    ``clock() -> s`` and ``sleep(s)`` are injected; ``on_health(healthy, last_error)`` is called on each change.
    A usable sample is ready, not overflowed and has ``mag_ut``.
    """

    def __init__(
        self,
        read: Callable[[], Reading],
        *,
        clock: Callable[[], float],
        sleep: Callable[[float], None],
        backoff: Backoff | None = None,
        on_health: Callable[[bool, str], None] | None = None,
    ) -> None:
        self.read = read
        self.clock = clock
        self.sleep = sleep
        self.backoff = backoff or Backoff()
        self.on_health = on_health
        self.stats = ReadStats()
        self._failing_since: float | None = None

    def next(self, stop: Callable[[], bool] = lambda: False) -> Reading | None:
        """The next usable reading, or None once ``stop()`` is true (checked before every attempt).

        Raises ``SensorReadError`` after ``Backoff.give_up_after`` consecutive failures, when that is set."""
        polls = 0
        while not stop():
            self.stats.attempts += 1
            try:
                reading = self.read()
            except OSError as exc:
                self._fail(_cause(exc), str(exc), stop)
                polls = 0
                continue
            if not reading.ready or (reading.mag_ut is None and not reading.overflow):
                polls += 1
                self.stats.not_ready += 1
                if polls >= self.backoff.max_polls:
                    self._fail(STALLED, f"no new data after {polls} polls", stop)
                    polls = 0
                elif self.backoff.poll_s:
                    self.sleep(self.backoff.poll_s)
                continue
            if reading.overflow:
                self.stats.overflows += 1
                continue
            self._succeed()
            return reading
        return None

    def _fail(self, cause: str, message: str, stop: Callable[[], bool]) -> None:
        stats = self.stats
        stats.errors += 1
        stats.errors_by_cause[cause] = stats.errors_by_cause.get(cause, 0) + 1
        stats.consecutive_failures += 1
        stats.last_error = message
        now = self.clock()
        if self._failing_since is None:
            self._failing_since = now
            log.warning("sensor read failed (%d so far): %s; backing off", stats.errors, message)
        if stats.healthy and stats.consecutive_failures >= self.backoff.unhealthy_after:
            self._set_health(False)
        limit = self.backoff.give_up_after
        if limit is not None and stats.consecutive_failures >= limit:
            raise SensorReadError(
                errno.EIO,
                f"no usable reading after {stats.consecutive_failures} failures in a row "
                f"over {now - self._failing_since:.2f} s; last: {message}",
            )
        if not stop():
            delay = self.backoff.delay_s(stats.consecutive_failures)
            self.sleep(delay)
            stats.waited_s += delay

    def _succeed(self) -> None:
        self.stats.samples += 1
        self.stats.consecutive_failures = 0
        self._failing_since = None
        if not self.stats.healthy:
            self._set_health(True)

    def _set_health(self, healthy: bool) -> None:
        self.stats.healthy = healthy
        if healthy:
            log.info("sensor healthy again after %d errors in all", self.stats.errors)
        else:
            log.warning(
                "sensor unhealthy after %d failures in a row: %s",
                self.stats.consecutive_failures,
                self.stats.last_error,
            )
        if self.on_health is not None:
            self.on_health(healthy, "" if healthy else self.stats.last_error)
