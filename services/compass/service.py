"""``magnet compass``: apply each device's calibration to its raw batches, tilt-compensate with the accelerometer (or
fuse with the gyroscope), add the WMM declination, and publish one heading message per raw batch on
``<prefix>/<device>/heading`` (and to every other sink turned on: ``services.compass.sinks``).

On start it queries every stored calibration (``<prefix>/*/calibration``) and then follows new ones (subscriber);
it asks for every one again when a calibrator's liveliness token appears (one that came up or came back after that
query: its start-up publication of its records in force reached no link of ours when our session opened first); a
device with none is asked for again now and then, and meanwhile gets headings from its raw field (flag CALIBRATED
clear). Zenoh delivers into channels; this process's own loop drains them and moves bytes and clocks in
and out of the compass's core (``magnet.compass.CompassCore``): decode -> step -> encode -> put, never inside a
callback; every handler runs through ``services.common.guard`` (a failure drops and counts the messages it held, or
answers the query with an error; the loop goes on). Counters (received, published, dropped by cause) answer on
``<prefix>/@status/<name>``, from Zenoh's thread with what the loop last wrote (``services.common.status_board``: a
status never waits for a drain; behind a router on a session of its own, never behind raw messages); ``--metrics``
serves what the loop writes on a second board, never the core. The options are in ``services.compass.settings``;
docs/compass.md follows one sample.
"""

from __future__ import annotations

import argparse
import contextlib
import datetime
import gc
import logging
import threading
import time
from typing import Any

import zenoh

from magnet import wire
from magnet.compass import CompassCore
from magnet.earth.expected import earth_at
from magnet.fleet.places import Places
from services.common import metrics
from services.common.allocator import BurstTrim
from services.common.endpoint import use_local_pipeline
from services.common.guard import Guard
from services.common.status_board import StatusBoard
from services.common.zenoh_session import (
    drain,
    open_session,
    payload_bytes,
    queries_session,
    raw_session,
    stop_event,
)
from services.compass.intake import PayloadIntake
from services.compass.settings import (
    ZENOH_DEFAULTS,
    CompassSettings,
    add_arguments,
    load_trusted_keys,
    settings_from_args,
)
from services.compass.sinks import open_sinks

__all__ = ["CompassSettings", "add_arguments", "build_core", "run", "run_compass"]

log = logging.getLogger("magnet.compass")

Samples = zenoh.Subscriber[zenoh.Handler[zenoh.Sample]]
Queries = zenoh.Queryable[zenoh.Handler[zenoh.Query]]
Replies = zenoh.Handler[zenoh.Reply]

MAX_DRAIN = 8000  # raw messages computed together at most
#: samples computed together, about: the drain limit follows the batch size seen. More: fewer, longer vqf calls per
#: device (about 4 us per call); fewer: arrays that stay in the cache, and earlier headings
DRAIN_SAMPLES = 30_000
#: the garbage collector's first threshold: a drain makes tens of thousands of short-lived containers (the unpacked
#: messages); at the default 700 the collector ran several times per drain over every long-lived object
GC_THRESHOLD = 200_000
#: raw messages queued between zenoh and the intake's pump (which empties it at once into a queue bounded in bytes,
#: ``services.compass.intake``): a burst of large messages is held there, not here
CHANNEL_CAPACITY = 256
#: raw payload bytes decoded together at most (a drain of 2.5 MB bombs stays a few of them)
DRAIN_BYTES = 8 * 1024 * 1024
#: seconds a drain may take: a slower one (a flood of new ids: each new device's state made) shrinks the next, so
#: the status and the stop signal, seen between drains, wait at most about this long (issue 32)
STEP_BUDGET_S = 0.25
#: how often at most the loop writes what --metrics serves (s): scrapes come every few seconds, and a vehicle's report
#: costs more than the status the status board gets 20 times a second
METRICS_REFRESH_S = 1.0
#: a drain and what still waits of this many raw messages is a burst (a flood, a backlog), and so is a step whose
#: intake refused any (payloads over a raw message's size: bombs of MBs that Zenoh reassembled in the heap): the freed
#: heap is given back at most every ``TRIM_BUSY_S`` while bursts last and once after, and every ``TRIM_S`` anyway
#: (``allocator.BurstTrim``): a flood's drains left 3-15 MB of the heap's middle freed but kept, more the further
#: the compass fell behind; 20 bombs alone 8 MB until the next periodic trim. Every 0.25 s rather than 1 s: bombs
#: freed within a second were still there when sampled (rounds' highest 72-81 MB against 73-90, a trim 2-10 ms)
TRIM_BUSY_MESSAGES, TRIM_BUSY_S, TRIM_S = 500, 0.25, 10.0
REQUERY_S = 5.0  # how often to ask again for the calibration of a device that has none
REQUERY_REFUSED_S = 1.0  # how often at most to ask the calibrators again after refusing a calibration
#: how often at most to ask for every calibration again because calibrators' tokens appeared (many at once: one query)
REQUERY_JOINED_S = 1.0
#: with no raw message waiting the loop waits this long at most for one (calibrations, tokens and queries are seen
#: between drains); it wakes as soon as one arrives
IDLE_WAIT_S = 0.005


def add_compass_arguments(parser: argparse.ArgumentParser) -> None:
    add_arguments(parser)
    metrics.add_metrics_argument(parser)


def metrics_status(core: CompassCore, name: str) -> dict[str, Any]:
    """What ``--metrics`` serves (made on the loop's thread, written on the loop's metrics board): the status, the
    open alerts by kind and every vehicle's report."""
    alerts: dict[str, int] = {}
    for alert in core.watch.open_alerts():
        alerts[alert.kind.value] = alerts.get(alert.kind.value, 0) + 1
    status = core.status(name).to_dict()
    vehicles = {v: r.to_dict() for v in core.vehicles.known() if (r := core.vehicle_report(v)) is not None}
    return {**status, "devices": {"calibrated": status["calibrations"]}, "alerts_open": alerts, "vehicles": vehicles}


def run_compass(args: argparse.Namespace) -> int:
    """``magnet compass``: the settings from the options, then ``run``."""
    if getattr(args, "metrics", None):
        metrics.parse_address(args.metrics)  # a bad address ends here, before anything is opened
    use_local_pipeline(args)  # no Zenoh option given: serve the running magnet up
    return run(settings_from_args(args), getattr(args, "metrics", None))


def build_core(settings: CompassSettings) -> CompassCore:
    """The compass's core from its settings (the trusted keys read from their files)."""
    places = Places(
        {entry.device: entry for entry in settings.places},
        settings.location,
        settings.date,
        max_reported=settings.max_devices,
    )
    return CompassCore(settings.core, places, load_trusted_keys(settings.trust))


def run(settings: CompassSettings, metrics_address: str | None = None) -> int:
    core = build_core(settings)
    if core.calibrations.trusted.enabled:
        log.info("compass applies only calibrations signed by key(s) %s", ", ".join(core.calibrations.trusted.key_ids))
    today = settings.date or datetime.datetime.now(datetime.UTC).date()
    declination = earth_at(settings.location, today).declination_deg
    stop = stop_event()
    prefix, devices, name = settings.zenoh.prefix, settings.devices, settings.name
    with open_session(settings.zenoh, ZENOH_DEFAULTS) as session, contextlib.ExitStack() as declared:
        declared.enter_context(session.liveliness().declare_token(wire.liveliness_key(prefix, "compass", name)))
        intake = PayloadIntake()
        raw_link = raw_session(declared, session, settings.zenoh, ZENOH_DEFAULTS)  # behind a router: small batches
        raw_sub = raw_link.declare_subscriber(f"{prefix}/{devices}/raw", zenoh.handlers.FifoChannel(CHANNEL_CAPACITY))
        pump = threading.Thread(
            target=intake.pump, args=(raw_sub.handler, zenoh.ZError), name="raw-intake", daemon=True
        )
        declared.callback(pump.join, 2.0)
        declared.enter_context(raw_sub)  # undeclared before the join above: that ends the pump
        pump.start()
        ends = _Ends(
            raw=intake,
            calibrations=declared.enter_context(
                session.declare_subscriber(f"{prefix}/{devices}/calibration", zenoh.handlers.FifoChannel(1024))
            ),
            alerts=declared.enter_context(
                session.declare_queryable(f"{prefix}/{devices}/{wire.Kind.ALERT.value}", zenoh.handlers.FifoChannel(64))
            ),
            vehicles=declared.enter_context(
                session.declare_queryable(wire.vehicle_key(prefix, "*"), zenoh.handlers.FifoChannel(64))
            ),
            calibrators=declared.enter_context(
                session.liveliness().declare_subscriber(
                    wire.liveliness_key(prefix, "calibrator", "*"), zenoh.handlers.FifoChannel(256), history=True
                )
            ),
        )
        log.info(
            "compass %s: serving %s/%s (shard %s), declination %.2f deg",
            name,
            prefix,
            devices,
            settings.shard,
            declination,
        )
        loop = _Loop(session, core, settings, metrics_address is not None)
        declared.callback(loop.close)
        status_session = queries_session(declared, session, settings.zenoh)  # behind a router: a link of its own
        declared.enter_context(status_session.declare_queryable(wire.status_key(prefix, name), loop.board.answer))
        if loop.metrics_board is not None:  # what the loop wrote, never its state (scrapes run on their own thread)
            metrics.start(metrics_address, "compass", loop.metrics_board.read)
        gc.collect()
        gc.freeze()  # what exists now (modules, settings, places) lives as long as the process: never scanned again
        gc.set_threshold(GC_THRESHOLD, 20, 20)
        while not stop.is_set():
            if not loop.step(ends, name):
                intake.wait(IDLE_WAIT_S)
    log.info("compass stopped: %s", core.status(name).to_dict())
    return 0


class _Ends:
    """The compass's declarations the loop drains: raw batches, calibrations, alert and vehicle queries (the status
    is answered from Zenoh's thread: ``services.common.status_board``)."""

    def __init__(
        self,
        raw: PayloadIntake,
        calibrations: Samples,
        alerts: Queries,
        vehicles: Queries | None = None,
        calibrators: Samples | None = None,
    ) -> None:
        self.raw, self.calibrations, self.alerts = raw, calibrations, alerts
        self.vehicles, self.calibrators = vehicles, calibrators


class _Loop:
    """One compass loop's session work: calibration queries and their replies, headings published."""

    def __init__(
        self, session: zenoh.Session, core: CompassCore, settings: CompassSettings, with_metrics: bool = False
    ) -> None:
        self.session, self.core = session, core
        self.prefix, self.devices = settings.zenoh.prefix, settings.devices
        self.sinks = open_sinks(session, settings)
        self.asked = self.asked_refused = self.asked_joined = time.monotonic()
        self.pending: list[tuple[float, Replies]] = [(self.asked + 3.0, self._ask(3.0))]
        self.joined = False  # a calibrator's token appeared since the last query for every calibration
        self.drain_limit = self.time_limit = MAX_DRAIN
        self.guard = Guard("compass", log, core.drops)
        self.trim = BurstTrim(TRIM_BUSY_MESSAGES, TRIM_S, TRIM_BUSY_S)
        #: the status, answered from Zenoh's thread with what the loop last wrote (services.common.status_board)
        self.board = StatusBoard(wire.status_key(self.prefix, settings.name), self.guard)
        self.board.write(core.status(settings.name).to_dict())
        #: what ``--metrics`` serves (status, open alerts, vehicles), written by the loop at most every
        #: ``METRICS_REFRESH_S`` and only with --metrics: a scrape reads it and never touches the core
        self.metrics_board: StatusBoard | None = None
        if with_metrics:
            self.metrics_board = StatusBoard(self.board.key, self.guard, refresh_s=METRICS_REFRESH_S)
            self.metrics_board.write(metrics_status(core, settings.name))

    def step(self, ends: _Ends, name: str) -> bool:
        """One round of the loop, every handler through the guard (none ends the compass); False when no raw
        batches were waiting."""
        self.guard.run("calibration", self.calibrations, ends.calibrations)
        for token in drain(ends.calibrators, 64) if ends.calibrators is not None else []:
            alive = token.kind == zenoh.SampleKind.PUT
            self.core.on_calibrator(str(token.key_expr), alive, time.time_ns())
            self.joined = self.joined or alive
        self._ask_joined()
        self.guard.run("alert", self.alerts, ends.alerts)
        for query in drain(ends.vehicles, 16) if ends.vehicles is not None else []:
            self.guard.answer("query:vehicle", query, self.answer_vehicles)
            query.drop()
        refused = self.core.drops.total
        ends.raw.hand_over_drops(self.core.drops, log)
        refused = self.core.drops.total - refused  # by the intake: over a raw message's size, or past its bytes
        samples = ends.raw.take(min(self.drain_limit, self.time_limit), DRAIN_BYTES)
        if samples:
            started = time.perf_counter()
            self.guard.run("raw", self.headings_of, samples, count=len(samples))
            self._pace(len(samples), time.perf_counter() - started)
        self.trim.after_step(len(samples) + len(ends.raw), burst=refused > 0)  # a backlog, bombs: bursts too
        if self.board.due():
            self.board.write(self.core.status(name).to_dict())
        if self.metrics_board is not None and self.metrics_board.due():
            self.metrics_board.write(metrics_status(self.core, name))
        return bool(samples)

    def _pace(self, taken: int, took_s: float) -> None:
        """A drain slower than ``STEP_BUDGET_S`` (thousands of new devices at once) makes the next ones as small as
        fit the budget (the status and the stop signal are seen between drains); fast ones let it grow back, twice
        as large each time, up to ``MAX_DRAIN``."""
        if took_s > STEP_BUDGET_S:
            self.time_limit = max(100, int(taken * STEP_BUDGET_S / took_s))
        elif took_s < STEP_BUDGET_S / 2:
            self.time_limit = min(MAX_DRAIN, 2 * self.time_limit)

    def _ask(self, timeout: float, devices: str | None = None) -> Replies:
        return self.session.get(f"{self.prefix}/{devices or self.devices}/calibration", timeout=timeout)

    def _ask_refused(self) -> None:
        """Ask the calibrators again for the calibrations of devices whose calibration was just refused (a forged or
        stale one may have hidden a genuine update), at most every REQUERY_REFUSED_S."""
        now = time.monotonic()
        if not len(self.core.calibrations.refused) or now - self.asked_refused < REQUERY_REFUSED_S:
            return
        self.asked_refused = now
        refused, overflow = self.core.calibrations.take_refused()
        if overflow or len(refused) > 8:
            refused = [self.devices]
        self.pending += [(now + 2.0, self._ask(2.0, device)) for device in refused]

    def _ask_joined(self) -> None:
        """Ask for every calibration again when a calibrator's token appeared, at most every REQUERY_JOINED_S (a
        token seen sooner waits for its turn, never dropped). Its records in force may never have reached this
        compass: when our session opened before the calibrator listened, the start-up query found nobody, and the
        calibrator's start-up publication (``publish_in_force``) went out before Zenoh's retry linked us to it (1 s
        later or more). Raw batches of a device without a record make the compass ask again, but only once they
        come, and a record held that the calibrator replaced meanwhile would stay. The calibrator declares its
        token once it answers queries."""
        now = time.monotonic()
        if not self.joined or now - self.asked_joined < REQUERY_JOINED_S:
            return
        self.joined, self.asked_joined = False, now
        self.pending.append((now + 2.0, self._ask(2.0)))

    def _accept(self, sample: zenoh.Sample) -> None:
        self.guard.run(
            "calibration", self.core.accept_calibration, payload_bytes(sample), str(sample.key_expr), self.prefix
        )

    def calibrations(self, subscriber: Samples) -> None:
        """Take the calibrations published and the replies to queries that arrived; keep queries that may answer."""
        still, now = [], time.monotonic()
        for deadline, handler in self.pending:
            for reply in drain(handler, 10_000):
                if reply.ok is not None:
                    self._accept(reply.ok)
            if now < deadline:
                still.append((deadline, handler))
        self.pending = still
        for sample in drain(subscriber, 1000):
            self._accept(sample)
        self._ask_refused()

    def close(self) -> None:
        """Close every sink (the last opened first)."""
        for sink in reversed(self.sinks):
            sink.close()

    def headings_of(self, samples: list[tuple[str, bytes]]) -> None:
        """Compute and publish the headings of these raw (key, payload) pairs (a drain): decode -> step -> each
        sink's publish and tick (``services.compass.sinks``)."""
        if not self.core.keys.shard.everything:  # another shard's devices: dropped by key, before any decoding
            samples = [item for item in samples if self.core.keys.mine(item[0], self.prefix)]
        columns = self.core.decode(samples, self.prefix)
        out = self.core.step(columns, time.time_ns())
        for sink in self.sinks:
            sink.publish(columns, out, self.core)
        for sink in self.sinks:
            sink.tick(self.core)
        if len(columns.t_ns):
            metrics.observe_latency((time.time_ns() - int(columns.t_ns.max())) / 1e9)
        self._ask_missing(columns.devices)
        if columns.devices:
            batch = len(columns.t_ns) / len(columns.devices)
            self.drain_limit = int(min(MAX_DRAIN, max(100, DRAIN_SAMPLES / batch)))

    def alerts(self, queryable: Queries) -> None:
        """Publish the alerts raised or cleared; answer queries for the open ones."""
        for alert in self.core.watch.take():
            self.session.put(wire.key(self.prefix, alert.device, wire.Kind.ALERT), wire.pack(alert.to_message()))
        for query in drain(queryable, 16):
            self.guard.answer("query:alert", query, self.answer_alerts)
            query.drop()

    def answer_vehicles(self, query: zenoh.Query) -> None:
        """Each vehicle the query's key matches, its compasses compared (``magnet.vehicle``; docs/vehicles.md)."""
        asked = zenoh.KeyExpr(str(query.key_expr))
        for vehicle in self.core.vehicles.known():
            key = wire.vehicle_key(self.prefix, vehicle)
            if asked.intersects(zenoh.KeyExpr(key)):
                report = self.core.vehicle_report(vehicle)
                if report is not None:
                    query.reply(key, wire.pack({"v": wire.RECORD_VERSION, **report.to_dict()}))

    def answer_alerts(self, query: zenoh.Query) -> None:
        asked = zenoh.KeyExpr(str(query.key_expr))
        for alert in self.core.watch.open_alerts():
            key = wire.key(self.prefix, alert.device, wire.Kind.ALERT)
            if asked.intersects(zenoh.KeyExpr(key)):
                query.reply(key, wire.pack(alert.to_message()))

    def _ask_missing(self, seen: list[str]) -> None:
        """One query for every calibration when a device was seen without one (at most every REQUERY_S)."""
        now = time.monotonic()
        if now - self.asked < REQUERY_S or all(d in self.core.calibrations.in_force for d in seen):
            return
        self.asked = now
        self.pending.append((now + 2.0, self._ask(2.0)))
