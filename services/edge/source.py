"""The one shape of a ``magnet edge`` source (``Source``), and the clock that paces the sources that do not wait for
their data themselves (``ticked``).

A source is opened from the settings by its constructor (one row of ``services.edge.sources.SOURCES``), then:

- ``attach(session, events)``: once the edge's Zenoh session is open. A source that subscribes (ROS 2) declares on
  ``session``; a source whose devices appear while it runs or fail one by one (MAVLink, a chip on a bus) tells
  ``events`` (the edge's status: liveliness tokens per device and per unhealthy device, withdrawn when a device
  is forgotten). Others do nothing.
- ``batches(stop)``: the batches as they are due, one list per step (a batch per device that has one), until
  ``stop()`` is true or the source ends (a replay at the end of its recording).
- ``ids``: the devices known now (a MAVLink source adds them as vehicles appear).
- ``status()``: its read counters for the edge's status (``reads``): at least ``healthy``, ``attempts``,
  ``errors`` and ``last_error``; None for a simulated source, which cannot fail.
- ``close()``: undeclare what it declared and release what it opened (before the session closes).
"""

from __future__ import annotations

import time
from collections.abc import Callable, Iterator
from typing import Any, Protocol, runtime_checkable

import numpy as np
import zenoh

from magnet import wire

Stop = Callable[[], bool]
#: one step of a source paced by ``ticked``: (seq, end_ns: wall-clock ns of the batch's last sample, stop) -> batches
Take = Callable[[int, int, Stop], list[wire.RawBatch]]


class DeviceEvents(Protocol):
    """What a source tells the edge while it runs (the edge's status implements it)."""

    def on_health(self, healthy: bool, error: str) -> None:
        """The source's one device turned unhealthy (``error`` says why) or healthy again."""

    def device_seen(self, device: str) -> None:
        """A device appeared while running."""

    def device_health(self, device: str, healthy: bool) -> None:
        """One device of a source with many turned unhealthy or healthy again."""

    def device_gone(self, device: str) -> None:
        """A device that appeared while running fell silent and was forgotten: its tokens and place go."""


@runtime_checkable
class Source(Protocol):
    """Where ``magnet edge``'s samples come from (see the module)."""

    ids: list[str]

    def attach(self, session: zenoh.Session, events: DeviceEvents) -> None: ...

    def batches(self, stop: Stop) -> Iterator[list[wire.RawBatch]]: ...

    def status(self) -> dict[str, Any] | None: ...

    def close(self) -> None: ...


def stamp(n: int, end_ns: int, period_ns: int) -> np.ndarray:
    """(n,) int64 ns: n sample times ``period_ns`` apart ending at ``end_ns``."""
    return end_ns - period_ns * np.arange(n - 1, -1, -1, dtype=np.int64)


def ticks(period_s: float, stop: Stop) -> Iterator[int]:
    """Yields the wall-clock ns of each batch's end, paced at ``period_s``; never sleeps when behind."""
    start = time.monotonic()
    wall0 = time.time_ns()
    k = 0
    while not stop():
        k += 1
        target = start + k * period_s
        delay = target - time.monotonic()
        if delay > 0:
            time.sleep(delay)
        elif delay < -1.0:  # far behind (overload): resynchronize instead of bursting
            start = time.monotonic() - k * period_s
        yield wall0 + int((time.monotonic() - start) * 1e9)


def ticked(take: Take, period_s: float, stop: Stop) -> Iterator[list[wire.RawBatch]]:
    """The batches of ``take`` once every ``period_s`` (0: as fast as ``take`` returns, for a source that waits for
    its data), numbered from 0, until ``stop()``."""
    for seq, end_ns in enumerate(ticks(period_s, stop)):
        yield take(seq, end_ns, stop)
