"""The one loop that reads a sensor until it gives a usable sample: bounded backoff, counted errors, health.

``magnet edge`` and ``magnet sample`` both read through ``ReadLoop.next()``. A driver's ``read()`` retries a transfer
a few times (milliseconds) and then raises ``SensorReadError`` (an ``OSError``); this loop is the level above it,
with the same ``magnet.retry.RetryPolicy`` (``READ_BACKOFF`` unless told) and ``Health`` record:

- a failed read (any ``OSError``) is counted (``errors``, ``errors_by_cause``) and followed by a wait that doubles
  from the policy's ``initial_s`` up to its ``max_s``, so a dead bus costs at most about one read attempt per
  ``max_s`` seconds instead of a busy spin;
- a reading with nothing new (``ready == False``) is polled again after ``poll_s``; ``max_polls`` polls in a row
  without data count as one failure of cause ``stalled`` (a chip that stopped measuring);
- an overflowed reading is counted (``overflows``) and skipped;
- after ``unhealthy_after`` consecutive failures the loop is unhealthy; the next usable reading makes it healthy
  again; each change is reported once through ``on_health(healthy, last_error)``;
- with ``give_up_after`` set, that many consecutive failures raise ``SensorReadError`` (a one-shot command ends with
  a clear error); unset (the edge), the loop keeps trying until ``stop()`` is true.

Pure: the clock (seconds, monotonic) and the sleep are injected; nothing here touches threads, sockets or a bus.
"""

from __future__ import annotations

import errno
import logging
from collections.abc import Callable

from magnet.drivers.base import Reading, SensorReadError
from magnet.retry import READ_BACKOFF, Health, RetryPolicy, cause_of

log = logging.getLogger(__name__)

STALLED = "stalled"


class ReadLoop:
    """Reads ``read()`` (a driver's ``Sensor.read``) until a usable sample comes, per ``policy`` (a
    ``RetryPolicy``); what happened is counted in ``health`` (a ``Health``).

    ``clock() -> s`` and ``sleep(s)`` are injected; ``on_health(healthy, last_error)`` is called on each change.
    A usable sample is ready, not overflowed and has ``mag_ut``.
    """

    def __init__(
        self,
        read: Callable[[], Reading],
        *,
        clock: Callable[[], float],
        sleep: Callable[[float], None],
        policy: RetryPolicy = READ_BACKOFF,
        on_health: Callable[[bool, str], None] | None = None,
    ) -> None:
        self.read = read
        self.clock = clock
        self.sleep = sleep
        self.policy = policy
        self.on_health = on_health
        self.health = Health()
        self._failing_since: float | None = None

    def next(self, stop: Callable[[], bool] = lambda: False) -> Reading | None:
        """The next usable reading, or None once ``stop()`` is true (checked before every attempt).

        Raises ``SensorReadError`` after ``policy.give_up_after`` consecutive failures, when that is set."""
        polls = 0
        health = self.health
        while not stop():
            health.attempts += 1
            try:
                reading = self.read()
            except OSError as exc:
                self._fail(cause_of(exc), str(exc), stop)
                polls = 0
                continue
            if not reading.ready or (reading.mag_ut is None and not reading.overflow):
                polls += 1
                health.not_ready += 1
                if polls >= self.policy.max_polls:
                    self._fail(STALLED, f"no new data after {polls} polls", stop)
                    polls = 0
                elif self.policy.poll_s:
                    self.sleep(self.policy.poll_s)
                continue
            if reading.overflow:
                health.overflows += 1
                continue
            self._failing_since = None
            if health.succeeded():
                self._report()
            return reading
        return None

    def _fail(self, cause: str, message: str, stop: Callable[[], bool]) -> None:
        health = self.health
        changed = health.failed(cause, message, self.policy)
        now = self.clock()
        if self._failing_since is None:
            self._failing_since = now
            log.warning("sensor read failed (%d so far): %s; backing off", health.errors, message)
        if changed:
            self._report()
        if self.policy.gives_up(health.consecutive_failures):
            raise SensorReadError(
                errno.EIO,
                f"no usable reading after {health.consecutive_failures} failures in a row "
                f"over {now - self._failing_since:.2f} s; last: {message}",
            )
        if not stop():
            delay = self.policy.delay_s(health.consecutive_failures)
            self.sleep(delay)
            health.waited_s += delay

    def _report(self) -> None:
        health = self.health
        if health.healthy:
            log.info("sensor healthy again after %d errors in all", health.errors)
        else:
            log.warning(
                "sensor unhealthy after %d failures in a row: %s", health.consecutive_failures, health.last_error
            )
        if self.on_health is not None:
            self.on_health(health.healthy, "" if health.healthy else health.last_error)
