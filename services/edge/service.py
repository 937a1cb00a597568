"""``magnet edge``: read one device (real I2C chip, emulated chip, or simulator) or a simulated fleet, and publish
batches of raw samples on ``<prefix>/<device>/raw`` (see ``magnet.wire``).

Sources (``services.edge.sources``; each a ``services.edge.source.Source``, see docs/edge.md):
- ``--sensor NAME --bus N [--address A]``: a real chip through smbus2, read through the bounded read loop
  (``magnet.edge.readloop``): a failing bus is retried with a backoff capped at 1 s, every error counted.
- ``--sensor NAME --emulate``: the chip's register-level emulator (``magnet.emulators``) read through the same driver,
  its true field from a ``SensorStream`` (simulator) with the given hard iron, soft iron, noise and trajectory;
  ``--emulate-faults P`` (for tests) makes each transfer after set-up fail with probability P.
- ``--sensor sim --emulate``: the ``SensorStream`` directly, no register emulation.
- ``--emulate --devices N``: N simulated devices (``SimulatedDevices``, each its own hard and soft iron) named
  ``<ID>-000`` ... from one process.
- ``--replay FILE.csv [--speed X]``: a recording with the columns of ``magnet sample`` (``t_s``, ``mx,my,mz``, optional
  ``ax,ay,az`` and ``gx,gy,gz`` in rad/s) published at its own pace, X times faster, in batches of ``--batch``; the
  edge exits 0 at its end. Wire times keep the recording's intervals, starting from the wall clock at the start.

Health: liveliness tokens ``<prefix>/@alive/edge/<ID>`` and ``<prefix>/@alive/device/<device>`` while running, and
``<prefix>/@alive/device/<ID>/unhealthy`` while the sensor is unhealthy (3 failed reads in a row; withdrawn at the
next good read). Status: ``<prefix>/@status/edge-<ID>`` answers counters (``published_samples``, ``read_attempts``,
``read_errors``, ``healthy``, ``last_error``, ``reads``: the read loop's counters).

Emulated sources carry the simulator's true heading/pitch/roll in the message's ``truth``. On exit (``--duration`` or
a signal) it prints one JSON line: ``{"devices", "published_samples", "published_batches", "seconds", "read_errors",
"read_attempts", "healthy"}``.
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import functools
import json
import logging
import time
from collections.abc import Callable
from typing import Any, cast

import zenoh

from magnet import wire
from services.common import metrics
from services.common.endpoint import use_local_pipeline
from services.common.guard import Guard
from services.common.zenoh_session import open_session, session_mode, stop_event
from services.edge.settings import EdgeSettings, add_arguments
from services.edge.source import Source, stamp
from services.edge.sources import make_source

__all__ = ["EdgeSettings", "add_arguments", "run", "serve"]

log = logging.getLogger("magnet.edge")

FLEET_SLOTS = 20
MATCH_WAIT_S = 3.0  # at start, wait this long at most for a subscriber (so the first batches are not lost)
FLUSH_S = 0.3


def status_name(device: str) -> str:
    """The edge's name in ``<prefix>/@status/<name>``."""
    return f"edge-{device}"


def unhealthy_key(prefix: str, device: str) -> str:
    """Liveliness key declared while the device's sensor is unhealthy."""
    return wire.liveliness_key(prefix, "device", f"{device}/unhealthy")


#: new tokens declared for devices that appear while the edge runs, on one session of their own (behind a router),
#: before a new one: Zenoh keeps about 1.1 kB per token key a session declared until it closes (docs/front-door.md)
TOKENS_PER_SESSION = 8192
Opener = Callable[[], contextlib.AbstractContextManager[zenoh.Session]]


class EdgeStatus:
    """The edge's counters and health: answers status queries (from Zenoh's thread), holds the tokens of unhealthy
    devices and of devices that appear while running (the ``DeviceEvents`` a source tells)."""

    def __init__(self, settings: EdgeSettings, source: Source | None = None) -> None:
        self.settings = settings
        self.ids = [settings.device] if source is None else list(source.ids)
        #: the devices the edge started with (a fleet's, a chip's), then at most --max-devices that appear running
        self.admitted = set(self.ids)
        self.started_with = frozenset(self.ids)
        self.forgotten = 0  # devices forgotten (silent) whose places were freed
        #: the raw key of each admitted device (the publisher's; dropped with a forgotten device)
        self.keys: dict[str, str] = {}
        self.limit = len(self.ids) + settings.max_devices
        self.reads: Callable[[], dict[str, Any] | None] = (lambda: None) if source is None else source.status
        self.published_samples = self.published_batches = 0
        self.session: zenoh.Session | None = None
        #: devices that appear while running (MAVLink): alive; and ``<device>/unhealthy`` while one is
        self.tokens: dict[str, zenoh.LivelinessToken] = {}
        self.token_keys: dict[str, str] = {}  # name -> the key of its token (declared again on a new session)
        self.opener: Opener | None = None
        self.own, self.declared_tokens, self.renewed = contextlib.ExitStack(), 0, 0
        self.guard = Guard("edge", log)  # no failing status query ends the edge (services.common.guard)

    def open(self, session: zenoh.Session, opener: Opener | None = None) -> None:
        """Declare from now on, on ``session``; with ``opener`` on sessions of their own, a new one after
        ``TOKENS_PER_SESSION`` tokens (the tokens declared again on it before the old one closes: none seen to go)."""
        self.opener = opener
        self.session = self.own.enter_context(opener()) if opener is not None else session

    def close(self) -> None:
        """Undeclare every token still declared; declare nothing more."""
        self.session = None
        for token in self.tokens.values():
            token.undeclare()  # lifetime: a device's tokens follow what it reports, not a block
        self.tokens.clear()
        self.own.close()

    def answer_status(self, query: zenoh.Query) -> None:
        """Answer one status query (from Zenoh's thread): the counters, or an error reply if that fails."""
        key = wire.status_key(self.settings.zenoh.prefix, status_name(self.settings.device))
        self.guard.answer("query:status", query, lambda q: q.reply(key, wire.pack(self.as_dict())))
        query.drop()

    def _token(self, name: str, key: str, declared: bool) -> None:
        """Declare the liveliness token ``key`` under ``name`` (once), or undeclare it."""
        if self.session is None:
            return
        if not declared and name in self.tokens:
            self.tokens.pop(name).undeclare()  # lifetime: declared while the device is unhealthy
            self.token_keys.pop(name, None)
        elif declared and name not in self.tokens:
            if self.opener is not None and self.declared_tokens >= TOKENS_PER_SESSION:
                self._renew(self.opener)
            self.tokens[name], self.token_keys[name] = self.session.liveliness().declare_token(key), key
            self.declared_tokens += 1

    def _renew(self, opener: Opener) -> None:
        old_tokens, old_own, self.own = self.tokens, self.own, contextlib.ExitStack()
        self.session = self.own.enter_context(opener())
        self.tokens = {name: self.session.liveliness().declare_token(self.token_keys[name]) for name in old_tokens}
        for token in old_tokens.values():
            token.undeclare()  # lifetime: the same keys are alive on the new session already
        old_own.close()
        self.declared_tokens, self.renewed = 0, self.renewed + 1  # new ones: those declared again are bounded anyway
        log.info("a new session for the devices' liveliness tokens (%d declared again)", len(self.tokens))

    def on_health(self, healthy: bool, error: str) -> None:
        """Declare ``unhealthy_key`` when the sensor turns unhealthy, undeclare it when it recovers."""
        self.device_health(self.settings.device, healthy)

    def admit(self, device: str, n: int = 1) -> bool:
        """Whether the edge publishes ``device``: one it started with or admitted, or a new one within
        ``--max-devices`` (admitted now); else False, ``n`` batches of it counted as dropped (``devices:limit``,
        the first logged). The devices already admitted are never affected."""
        if device in self.admitted:
            return True
        if len(self.admitted) < self.limit:
            self.admitted.add(device)
            if device not in self.ids:
                self.ids.append(device)
            return True
        if n and self.guard.drops.count("devices:limit", n):
            log.warning(
                "more than %d devices appeared: %s and any other new id dropped (counted in status "
                "dropped[devices:limit]; raise --max-devices if they are genuine)",
                self.settings.max_devices,
                device,
            )
        return False

    def device_seen(self, device: str) -> None:
        """A device that appeared while running: declare its liveliness token (within ``--max-devices``)."""
        if self.admit(device, 0):
            self._token(device, wire.liveliness_key(self.settings.zenoh.prefix, "device", device), True)

    def device_health(self, device: str, healthy: bool) -> None:
        """Declare ``unhealthy_key`` of one admitted device while it is unhealthy."""
        if device in self.admitted:
            self._token(f"{device}/unhealthy", unhealthy_key(self.settings.zenoh.prefix, device), not healthy)

    def device_gone(self, device: str) -> None:
        """A device that appeared while running was forgotten by its source (silent): its tokens are withdrawn and
        its place under ``--max-devices`` is free; one the edge started with keeps both."""
        if device in self.started_with or device not in self.admitted:
            return
        self.admitted.discard(device)
        self.forgotten += 1
        if device in self.ids:
            self.ids.remove(device)
        self._token(f"{device}/unhealthy", "", False)
        self._token(device, "", False)
        self.keys.pop(device, None)

    def as_dict(self) -> dict[str, Any]:
        reads = self.reads()
        return {
            "v": wire.RECORD_VERSION,
            "service": "edge",
            "name": status_name(self.settings.device),
            "device": self.settings.device,
            "devices": len(self.ids),
            "sensor": self.settings.sensor_name,
            "healthy": True if reads is None else reads["healthy"],
            "published_samples": self.published_samples,
            "published_batches": self.published_batches,
            "read_attempts": 0 if reads is None else reads["attempts"],
            "read_errors": 0 if reads is None else reads["errors"],
            "last_error": "" if reads is None else reads["last_error"],
            "reads": reads,
            "dropped": dict(self.guard.drops.counts),
            "forgotten": self.forgotten,
        }

    def summary(self, seconds: float) -> dict[str, Any]:
        """The JSON line printed at exit."""
        status = self.as_dict()
        return {
            "devices": len(self.ids),
            "published_samples": self.published_samples,
            "published_batches": self.published_batches,
            "seconds": round(seconds, 3),
            "read_errors": status["read_errors"],
            "read_attempts": status["read_attempts"],
            "healthy": status["healthy"],
        }


def _wait_for_subscribers(publisher: zenoh.Publisher, timeout_s: float) -> None:
    deadline = time.monotonic() + timeout_s
    while not _matching(publisher) and time.monotonic() < deadline:
        time.sleep(0.02)


def _matching(publisher: zenoh.Publisher) -> bool:
    """Whether a subscriber matches (zenoh 1.10's stub says ``matching_status`` is a bool: it is a MatchingStatus)."""
    return cast(zenoh.MatchingStatus, publisher.matching_status).matching


def _declare(session: zenoh.Session, settings: EdgeSettings, status: EdgeStatus, stack: contextlib.ExitStack) -> None:
    """Liveliness tokens and the status queryable (answered from Zenoh's thread), undeclared when ``stack`` ends."""
    prefix = settings.zenoh.prefix
    liveliness = session.liveliness()
    stack.enter_context(liveliness.declare_token(wire.liveliness_key(prefix, "edge", settings.device)))
    for device in status.ids:
        stack.enter_context(liveliness.declare_token(wire.liveliness_key(prefix, "device", device)))
    key = wire.status_key(prefix, status_name(settings.device))
    stack.enter_context(session.declare_queryable(key, status.answer_status))


class Publisher:
    """Puts each batch on its device's raw key; a fleet's devices spread evenly over the period (batch / rate), each
    slot stamped when it goes out (real devices do not tick together)."""

    def __init__(self, session: zenoh.Session, settings: EdgeSettings, status: EdgeStatus) -> None:
        self.session, self.status = session, status
        self.period_s = settings.batch / settings.rate_hz
        self.prefix = settings.zenoh.prefix
        self.keys = status.keys  # the status drops a forgotten device's key with its place
        self.keys.update({d: wire.key(self.prefix, d, wire.Kind.RAW) for d in status.ids})
        self.slots = min(len(status.ids), FLEET_SLOTS) if settings.devices else 1
        self.sample_ns = int(1e9 / settings.rate_hz)
        self.block = zenoh.CongestionControl.BLOCK  # raw samples wait for a congested link rather than vanish
        self.version = settings.wire_version
        self.location = settings.location
        self.vehicle = settings.vehicle

    def put(self, batches: list[wire.RawBatch]) -> None:
        tick = time.monotonic()
        for slot in range(self.slots):
            if slot:
                delay = tick + slot * self.period_s / self.slots - time.monotonic()
                if delay > 0:
                    time.sleep(delay)
                now_ns = time.time_ns()
            for batch in batches[slot :: self.slots]:
                if slot:
                    batch = dataclasses.replace(batch, t_ns=stamp(len(batch), now_ns, self.sample_ns))
                if self.location is not None and batch.location is None:
                    batch = dataclasses.replace(batch, location=self.location)
                if self.vehicle and not batch.vehicle:
                    batch = dataclasses.replace(batch, vehicle=self.vehicle)
                key = self.keys.get(batch.device)
                if key is None:
                    if not self.status.admit(batch.device):
                        continue
                    key = self.keys[batch.device] = wire.key(self.prefix, batch.device, wire.Kind.RAW)
                self.session.put(key, wire.encode_raw(batch, self.version), congestion_control=self.block)
                self.status.published_samples += len(batch)
                self.status.published_batches += 1


def serve(settings: EdgeSettings, metrics_address: str | None = None) -> int:
    """Run the edge until ``settings.duration_s``, a signal or the source's end; prints the summary line; returns the
    exit status."""
    source = make_source(settings)
    status = EdgeStatus(settings, source)
    metrics.start(metrics_address, "edge", lambda: {**status.as_dict(), "devices": len(status.ids)})
    stop = stop_event()
    with open_session(settings.zenoh) as session, contextlib.ExitStack() as stack:
        stack.callback(source.close)  # last: after the edge's own declarations, before the session closes
        own = session_mode(settings.zenoh) == "client"  # behind a router: the tokens on sessions of their own
        status.open(session, functools.partial(open_session, settings.zenoh) if own else None)
        stack.callback(status.close)
        _declare(session, settings, status, stack)
        source.attach(session, status)
        # one declared publisher, only to wait for a subscriber; data goes by session.put (measured: a declared
        # publisher per device costs several times the CPU at 10,000 messages/s)
        first_device = status.ids[0] if status.ids else settings.device
        first = stack.enter_context(
            session.declare_publisher(wire.key(settings.zenoh.prefix, first_device, wire.Kind.RAW))
        )
        log.info(
            "edge: %d device(s), %s at %.1f Hz, batches of %d",
            len(status.ids),
            settings.sensor_name,
            settings.rate_hz,
            settings.batch,
        )
        _wait_for_subscribers(first, MATCH_WAIT_S)  # devices that appear later: their subscribers match --device's
        started = time.monotonic()
        deadline = None if settings.duration_s is None else started + settings.duration_s

        def done() -> bool:
            return stop.is_set() or (deadline is not None and time.monotonic() >= deadline)

        publisher = Publisher(session, settings, status)
        for batches in source.batches(done):
            publisher.put(batches)
        seconds = time.monotonic() - started
        time.sleep(FLUSH_S)  # let the last batches leave before the declarations and the session end
    print(json.dumps(status.summary(seconds)), flush=True)
    return 0


def add_edge_arguments(parser: argparse.ArgumentParser) -> None:
    add_arguments(parser)
    metrics.add_metrics_argument(parser)


def run(args: argparse.Namespace) -> int:
    if getattr(args, "metrics", None):
        metrics.parse_address(args.metrics)  # a bad address ends here, before anything is opened
    use_local_pipeline(args)  # no Zenoh option given: publish into the running magnet up
    return serve(EdgeSettings.from_args(args), getattr(args, "metrics", None))
