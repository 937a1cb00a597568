"""``magnet compass``: apply each device's calibration to its raw batches, tilt-compensate with the accelerometer, add
the WMM declination, and publish one heading message per raw batch on ``<prefix>/<device>/heading``.

On start it queries every stored calibration (``<prefix>/*/calibration``) and then follows new ones (subscriber);
a device with none is asked for again now and then, and meanwhile gets headings from its raw field (flag
CALIBRATED clear). Zenoh delivers into channels; this process's own loop drains them, decodes, computes a whole
drain of batches at once (``magnet.compass.compute_headings``, vectorized over every sample of every device) and
publishes, never inside a callback; every handler runs through ``services.common.guard`` (a failure drops and
counts the messages it held, or answers the query with an error; the loop goes on). Counters (received, published,
dropped by cause) answer on ``<prefix>/@status/<name>``.

The options and settings are in ``services.compass.settings``, the calibrations in force (trust, staleness, shard)
in ``services.compass.calibrations``, the computation (no zenoh) in ``services.compass.core``; this module is the
Zenoh shell.
"""

from __future__ import annotations

import argparse
import gc
import logging
import time
from typing import Any

import zenoh

from magnet import wire
from magnet.bounded import Recent
from magnet.fleet import Places
from services.common import metrics
from services.common.guard import Guard
from services.common.zenoh_session import drain, open_session, payload_bytes, stop_event
from services.compass.core import Compass, CompassStatus, HeadingColumns
from services.compass.ros2 import Ros2Compass
from services.compass.settings import (
    CompassSettings,
    add_arguments,
    load_trusted_keys,
    settings_from_args,
)
from services.compass.watch import FleetWatch

__all__ = ["Compass", "CompassSettings", "CompassStatus", "HeadingColumns", "add_arguments", "run", "run_compass"]

log = logging.getLogger("magnet.compass")

MAX_DRAIN = 8000  # raw messages computed together at most
#: samples computed together, about: the drain limit follows the batch size seen. More: fewer, longer vqf calls per
#: device (about 4 us per call); fewer: arrays that stay in the cache, and earlier headings
DRAIN_SAMPLES = 30_000
#: the garbage collector's first threshold: a drain makes tens of thousands of short-lived containers (the unpacked
#: messages); at the default 700 the collector ran several times per drain over every long-lived object
GC_THRESHOLD = 200_000
CHANNEL_CAPACITY = 65536  # raw messages queued between zenoh and this loop
REQUERY_S = 5.0  # how often to ask again for the calibration of a device that has none
REQUERY_REFUSED_S = 1.0  # how often at most to ask the calibrators again after refusing a calibration
IDLE_SLEEP_S = 0.0003
#: the compass puts a drain's headings at once (thousands of messages): room for them in each link's queue (16
#: batches of 64 kB, Zenoh's most; its default is 2), and up to 20 ms for a busy machine's sending thread to make room
#: before a heading is dropped (default 1 ms). A subscriber that stays slow still loses headings, never the compass's
#: time for long. A --config file replaces these.
ZENOH_DEFAULTS = {
    "transport/link/tx/queue/size/data": "16",
    "transport/link/tx/queue/congestion_control/drop/wait_before_drop": "20000",
}


def add_compass_arguments(parser: argparse.ArgumentParser) -> None:
    add_arguments(parser)
    metrics.add_metrics_argument(parser)


def _metrics_status(compass: Compass, name: str) -> dict[str, Any]:
    alerts: dict[str, int] = {}
    for alert in compass.watch.open_alerts():
        alerts[alert.kind.value] = alerts.get(alert.kind.value, 0) + 1
    status = compass.status(name).to_dict()
    return {**status, "devices": {"calibrated": status["calibrations"]}, "alerts_open": alerts}


def run_compass(args: argparse.Namespace) -> int:
    """``magnet compass``: the settings from the options, then ``run``."""
    if getattr(args, "metrics", None):
        metrics.parse_address(args.metrics)  # a bad address ends here, before anything is opened
    return run(settings_from_args(args), getattr(args, "metrics", None))


def run(settings: CompassSettings, metrics_address: str | None = None) -> int:
    default, date, fleet = settings.places
    places = Places(fleet, default, date, settings.earth, max_reported=settings.max_devices)
    watch = FleetWatch(places, settings.drift, settings.max_devices)
    compass = Compass(
        settings.earth, settings.window, load_trusted_keys(settings.trust), watch, settings.shard, settings.max_devices
    )
    if compass.trusted.enabled:
        log.info("compass applies only calibrations signed by key(s) %s", ", ".join(compass.trusted.key_ids))
    stop = stop_event()
    prefix, devices, name = settings.zenoh.prefix, settings.devices, settings.name
    with open_session(settings.zenoh, ZENOH_DEFAULTS) as session:
        token = session.liveliness().declare_token(wire.liveliness_key(prefix, "compass", name))
        raw_sub = session.declare_subscriber(f"{prefix}/{devices}/raw", zenoh.handlers.FifoChannel(CHANNEL_CAPACITY))
        cal_sub = session.declare_subscriber(f"{prefix}/{devices}/calibration", zenoh.handlers.FifoChannel(1024))
        status_q = session.declare_queryable(wire.status_key(prefix, name), zenoh.handlers.FifoChannel(64))
        alert_q = session.declare_queryable(
            f"{prefix}/{devices}/{wire.Kind.ALERT.value}", zenoh.handlers.FifoChannel(64)
        )
        log.info(
            "compass %s: serving %s/%s (shard %s), declination %.2f deg",
            name,
            prefix,
            devices,
            settings.shard,
            compass.earth.declination_deg,
        )
        loop = _Loop(session, compass, settings)
        if settings.ros2.enabled:
            loop.ros2 = Ros2Compass(session, settings.ros2, name, settings.max_devices)
        metrics.start(metrics_address, "compass", lambda: _metrics_status(compass, name))
        gc.collect()
        gc.freeze()  # what exists now (modules, settings, places) lives as long as the process: never scanned again
        gc.set_threshold(GC_THRESHOLD, 20, 20)
        while not stop.is_set():
            if not loop.step(cal_sub, status_q, alert_q, raw_sub, name):
                time.sleep(IDLE_SLEEP_S)
        if loop.ros2 is not None:
            loop.ros2.close()
        token.undeclare()
    log.info("compass stopped: %s", compass.status(name).to_dict())
    return 0


class _Loop:
    """One compass loop's session work: calibration queries and their replies, headings published."""

    def __init__(self, session: Any, compass: Compass, settings: CompassSettings) -> None:
        self.session, self.compass = session, compass
        self.prefix, self.devices = settings.zenoh.prefix, settings.devices
        self.heading_keys: Recent[str, str] = Recent(settings.max_devices)
        self.asked = self.asked_refused = time.monotonic()
        self.pending: list[tuple[float, Any]] = [(self.asked + 3.0, self._ask(3.0))]
        self.drain_limit = MAX_DRAIN
        self.ros2: Ros2Compass | None = None
        self.guard = Guard("compass", log, compass.drops)

    def step(self, cal_sub: Any, status_q: Any, alert_q: Any, raw_sub: Any, name: str) -> bool:
        """One round of the loop, every handler through the guard (none ends the compass); False when no raw
        batches were waiting."""
        self.guard.run("calibration", self.calibrations, cal_sub)
        for query in drain(status_q, 64):
            self.guard.answer("query:status", query, self.answer_status, name)
            query.drop()  # finalize now: the asker waits for it
        self.guard.run("alert", self.alerts, alert_q)
        samples = drain(raw_sub, self.drain_limit)
        if samples:
            self.guard.run("raw", self.headings_of, samples, count=len(samples))
        return bool(samples)

    def answer_status(self, query: Any, name: str) -> None:
        query.reply(wire.status_key(self.prefix, name), wire.pack(self.compass.status(name).to_dict()))

    def _ask(self, timeout: float, devices: str | None = None) -> Any:
        return self.session.get(f"{self.prefix}/{devices or self.devices}/calibration", timeout=timeout)

    def _ask_refused(self) -> None:
        """Ask the calibrators again for the calibrations of devices whose calibration was just refused (a forged or
        stale one may have hidden a genuine update), at most every REQUERY_REFUSED_S."""
        now = time.monotonic()
        if not (self.compass.refused or self.compass.refused_overflow) or now - self.asked_refused < REQUERY_REFUSED_S:
            return
        self.asked_refused = now
        refused = sorted(self.compass.refused)
        if self.compass.refused_overflow or len(refused) > 8:
            refused = [self.devices]
        self.compass.refused.clear()
        self.compass.refused_overflow = False
        self.pending += [(now + 2.0, self._ask(2.0, device)) for device in refused]

    def calibrations(self, cal_sub: Any) -> None:
        """Take the calibrations published and the replies to queries that arrived; keep queries that may answer."""
        still, now = [], time.monotonic()
        for deadline, handler in self.pending:
            for reply in drain(handler, 10_000):
                if reply.ok is not None:
                    self.guard.run(
                        "calibration",
                        self.compass.accept_calibration,
                        payload_bytes(reply.ok),
                        str(reply.ok.key_expr),
                        self.prefix,
                    )
            if now < deadline:
                still.append((deadline, handler))
        self.pending = still
        for sample in drain(cal_sub, 1000):
            self.guard.run(
                "calibration", self.compass.accept_calibration, payload_bytes(sample), str(sample.key_expr), self.prefix
            )
        self._ask_refused()

    def _payloads(self, samples: list[Any], keys: list[str]) -> list[tuple[str, bytes]]:
        """(key, payload bytes) of each sample; one larger than any raw message may be is dropped and counted
        without being copied out of zenoh (a drain of msgpack bombs would otherwise be copied all at once)."""
        limit = wire.RAW_LIMITS.payload_bytes
        items = []
        for sample, key in zip(samples, keys):
            payload = sample.payload
            if len(payload) > limit:
                self.compass.drops.drop(
                    wire.WireError("oversized", f"payload of {len(payload)} bytes exceeds {limit}"), "raw", log
                )
            else:
                items.append((key, payload.to_bytes()))
        return items

    def headings_of(self, samples: list[Any]) -> None:
        """Compute and publish the headings of these raw samples (a drain)."""
        keys = [str(s.key_expr) for s in samples]
        if not self.compass.shard.everything:  # another shard's devices: dropped by key, before any decoding
            mine = [i for i, k in enumerate(keys) if self.compass.mine(k, self.prefix)]
            samples, keys = [samples[i] for i in mine], [keys[i] for i in mine]
        columns = self.compass.decode_columns(self._payloads(samples, keys), self.prefix)
        for device, payload in zip(columns.devices, self.compass.encode(columns)):
            key = self.heading_keys.get(device) or self.heading_keys.setdefault(
                device, wire.key(self.prefix, device, wire.Kind.HEADING)
            )
            self.session.put(key, payload)  # measured: a declared publisher per device costs ~5x the CPU
            self.compass.published_batches += 1
        if self.ros2 is not None and self.compass.last is not None:
            self.ros2.publish(columns, self.compass.last, self.compass.calibrations)
            self.ros2.tick(self.compass.calibrations, self.compass.watch.open_alerts())
        if len(columns.t_ns):
            metrics.observe_latency((time.time_ns() - int(columns.t_ns.max())) / 1e9)
        self._ask_missing(columns.devices)
        if columns.devices:
            batch = len(columns.t_ns) / len(columns.devices)
            self.drain_limit = int(min(MAX_DRAIN, max(100, DRAIN_SAMPLES / batch)))

    def alerts(self, alert_q: Any) -> None:
        """Publish the alerts raised or cleared; answer queries for the open ones."""
        for alert in self.compass.watch.take():
            self.session.put(wire.key(self.prefix, alert.device, wire.Kind.ALERT), wire.pack(alert.to_message()))
        for query in drain(alert_q, 16):
            self.guard.answer("query:alert", query, self.answer_alerts)
            query.drop()

    def answer_alerts(self, query: Any) -> None:
        asked = zenoh.KeyExpr(str(query.key_expr))
        for alert in self.compass.watch.open_alerts():
            key = wire.key(self.prefix, alert.device, wire.Kind.ALERT)
            if asked.intersects(zenoh.KeyExpr(key)):
                query.reply(key, wire.pack(alert.to_message()))

    def _ask_missing(self, seen: list[str]) -> None:
        """One query for every calibration when a device was seen without one (at most every REQUERY_S)."""
        now = time.monotonic()
        if now - self.asked < REQUERY_S or all(d in self.compass.calibrations for d in seen):
            return
        self.asked = now
        self.pending.append((now + 2.0, self._ask(2.0)))
