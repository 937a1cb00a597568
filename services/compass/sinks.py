"""The compass's outputs: every drain's headings go to each ``Sink`` (docs/architecture.md, "Adding an output sink").

A sink is one class with three methods: ``publish`` (a drain's headings: the raw columns, the core's
``HeadingColumns`` of them, the core for what else it holds), ``tick`` (after every drain: periodic work such as
diagnostics) and ``close`` (undeclare what it declared). It is opened by a classmethod ``open(session, settings)``
that gives None when its options leave it off, and it is one line in ``SINKS``. The loop
(``services.compass.service``) calls them in that order, inside its guard (a failing sink drops and counts the
drain, the compass goes on). Members: the magnet heading messages on Zenoh (``ZenohHeadings``) and ROS 2
(``services.compass.ros2.Ros2Compass``).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Protocol

import zenoh

from magnet import wire
from magnet.bounded import Recent
from magnet.compass import CompassCore, HeadingColumns
from services.compass.ros2 import Ros2Compass
from services.compass.settings import CompassSettings


class Sink(Protocol):
    """Where the compass's headings go (see the module)."""

    def publish(self, columns: wire.RawColumns, out: HeadingColumns, core: CompassCore) -> None:
        """Send the headings ``out`` of one drain's raw ``columns`` (``core``: the calibrations in force, the
        counters, the wire's encoder)."""

    def tick(self, core: CompassCore) -> None:
        """After every drain: what the sink does now and then (diagnostics, flushing)."""

    def close(self) -> None:
        """Undeclare what the sink declared; the compass is stopping."""


class ZenohHeadings:
    """One heading message per raw batch on ``<prefix>/<device>/heading`` (``wire``), each counted as published."""

    def __init__(self, session: zenoh.Session, prefix: str, max_devices: int) -> None:
        self.session, self.prefix = session, prefix
        self.keys: Recent[str, str] = Recent(max_devices)

    @classmethod
    def open(cls, session: zenoh.Session, settings: CompassSettings) -> ZenohHeadings:
        return cls(session, settings.zenoh.prefix, settings.max_devices)

    def publish(self, columns: wire.RawColumns, out: HeadingColumns, core: CompassCore) -> None:
        for device, payload in zip(columns.devices, core.encode(columns, out)):
            key = self.keys.get(device) or self.keys.setdefault(
                device, wire.key(self.prefix, device, wire.Kind.HEADING)
            )
            self.session.put(key, payload)  # measured: a declared publisher per device costs ~5x the CPU
            core.counters.published_batches += 1

    def tick(self, core: CompassCore) -> None:
        """Nothing between drains."""

    def close(self) -> None:
        """Nothing declared (``session.put``)."""


#: (session, settings) -> the sink, or None when its options leave it off
SinkOpener = Callable[[zenoh.Session, CompassSettings], Sink | None]
#: every output of the compass, in the order each drain reaches them: a new sink is one class and one line here
SINKS: tuple[SinkOpener, ...] = (
    ZenohHeadings.open,
    Ros2Compass.open,
)


def open_sinks(session: zenoh.Session, settings: CompassSettings) -> list[Sink]:
    """The sinks ``settings`` turn on, opened on ``session``."""
    return [sink for sink in (opener(session, settings) for opener in SINKS) if sink is not None]
