"""The dashboard's Zenoh side: subscribers draining into ``FleetState``, and the queries the page asks for.

One thread (``Ingest.run``) drains every channel each ``tick_s``: liveliness of devices, progress, calibrations, drift
alerts (``<prefix>/<device>/alert``, and the compasses' open ones asked for now and then), and
headings, of which only the newest message of each device is decoded (1,000 devices at 10 Hz cost 4,000 decodes a
second at a 0.25 s tick, not 10,000). Devices someone is looking at get their own raw subscriber and every heading
sample. Raw messages of other devices pass through a small ring (``RAW_RING_CAPACITY``), read only for the sensor
name of a new device, each refused by its size before it is copied and let go before the next is taken.
Headings and progress wait in rings too (``RING_CAPACITY``), and each sample is copied and let go as it is read
(``copied``): a Zenoh sample keeps its receive buffer alive, and FIFOs of 65,536 held a flood's worth of them
(docs/front-door.md). The freed heap is given back every ``TRIM_S``. Zenoh keeps about 0.9 kB in a session for every
liveliness token key its subscriber was ever told of, until the session closes: with an ``opener`` (behind a router)
the tokens are taken on a session of their own, renewed after ``TOKENS_PER_SESSION`` of them.
"""

from __future__ import annotations

import contextlib
import logging
import threading
import time
from collections.abc import Callable
from typing import Any

import zenoh

from magnet import wire
from magnet.drift import alert_from_message
from services.common import metrics
from services.common.allocator import BurstTrim, give_back_now
from services.common.guard import Guard
from services.common.status_board import StatusBoard
from services.common.zenoh_session import Receiver, drain, payload_bytes
from services.dashboard.state import FleetState

log = logging.getLogger("magnet.dashboard")

CHANNEL_CAPACITY = 65536
#: liveliness samples one session takes before the ingest opens a new one for them (the module; 8,192 token keys are
#: about 7 MB kept by Zenoh; a MAVLink port's flood made 32,000 before the edge's bounds), beyond twice the tokens
#: alive (which a new session's history gives again: a fleet of more never renews at every step)
TOKENS_PER_SESSION = 8192
#: headings and progress wait in rings of this many messages (the oldest go first when a step is late: only each
#: device's newest is shown); a FIFO of 65,536 held every message of a flood, each pinning Zenoh's receive buffer.
#: Four floods of 20,000 ids (5,000/s) against a dashboard, a compass and a calibrator: RSS peaks 112-215 MB with
#: rings of 4,096, 97-115 with 1,024, 86-111 with 512 (back to 84-92 after each in every case)
RING_CAPACITY = 1024
#: raw messages of devices nobody watches wait in a ring of this many (read only for a new device's sensor name, which
#: every raw message of it repeats): each Zenoh sample pins its receive buffer, up to 4 MB for the soak's bombs, so
#: 64 pinned up to 80 MB between two steps (20 bombs); 8 pin at most 32 MB, and a device's next message names it
RAW_RING_CAPACITY = 8
#: the freed heap is given back to the system this often (s): floods and bursts of streams leave it fragmented
TRIM_S = 10.0
#: and after a step that took this many messages (a flood's burst), or refused a raw payload by its size (a bomb of
#: MBs), at most every ``TRIM_BUSY_S``, once more after the burst: a flood of 20,000 ids left 17-30 MB freed but kept
#: (Zenoh's receive buffers, decoded batches) for up to ``TRIM_S`` after each burst, which the soak saw as a round's
#: highest (a trim costs 2-12 ms)
TRIM_BUSY_MESSAGES = 500
TRIM_BUSY_S = 1.0
MAX_DRAIN = 100_000
QUERY_TIMEOUT_S = 5.0
REQUERY_S = 10.0
#: how often at most the ingest writes what --metrics serves (s): scrapes come every few seconds, and the counts walk
#: every row (10,000 at the default bound)
METRICS_REFRESH_S = 1.0


Subscriber = zenoh.Subscriber[zenoh.Handler[zenoh.Sample]]


def copied(handler: Receiver[zenoh.Sample], limit: int) -> list[tuple[str, bytes]]:
    """(key, payload) of up to ``limit`` samples a channel holds now, each sample let go as soon as it is copied: a
    Zenoh sample keeps the receive buffer it came in alive (up to 64 kB for a message of a few hundred bytes), so a
    step that held a drain's samples while it decoded held megabytes per thousand messages."""
    out: list[tuple[str, bytes]] = []
    while len(out) < limit:
        try:
            sample = handler.try_recv()
        except zenoh.ZError:
            break
        if sample is None:
            break
        out.append((str(sample.key_expr), payload_bytes(sample)))
    return out


class Ingest:
    """Feeds a FleetState from a zenoh session (``session`` already open; the caller closes it). A context manager:
    its subscribers are undeclared when the ``with`` block ends (after ``stop`` and the end of ``run``)."""

    def __init__(
        self,
        session: zenoh.Session,
        prefix: str,
        state: FleetState,
        tick_s: float = 0.25,
        metrics_board: StatusBoard | None = None,
        opener: Callable[[], contextlib.AbstractContextManager[zenoh.Session]] | None = None,  # the tokens' sessions
    ) -> None:
        self.session, self.prefix, self.state, self.tick_s = session, prefix, state, tick_s
        #: what ``--metrics`` serves (``FleetState.metrics_status``), written by this thread at most every
        #: ``METRICS_REFRESH_S`` (None: no --metrics): a scrape reads it and never walks the rows from its own thread
        self.metrics_board = metrics_board
        self.stop = threading.Event()
        self.declared = contextlib.ExitStack()
        fifo = zenoh.handlers.FifoChannel
        self.opener, self.tokens_seen, self.renewed = opener, 0, 0
        self.tokens_alive = 0  # puts less deletes since the session opened: its history gives them again
        self.alive_declared = contextlib.ExitStack()
        self.alive = self._alive()
        self.headings = self._subscribe(wire.Kind.HEADING, zenoh.handlers.RingChannel(RING_CAPACITY))
        self.progress = self._subscribe(wire.Kind.PROGRESS, zenoh.handlers.RingChannel(RING_CAPACITY))
        self.calibrations = self._subscribe(wire.Kind.CALIBRATION, fifo(4096))
        self.alerts = self._subscribe(wire.Kind.ALERT, fifo(4096))
        self.raw_any = self._subscribe(wire.Kind.RAW, zenoh.handlers.RingChannel(RAW_RING_CAPACITY))
        self.raw_watched: dict[str, tuple[Subscriber, contextlib.ExitStack]] = {}
        self.pending: list[tuple[float, zenoh.Handler[zenoh.Reply]]] = []
        self.asked_s = -REQUERY_S
        #: when the freed heap is given back (``give_back_now`` looked up at each trim: tests replace it)
        self.trim = BurstTrim(TRIM_BUSY_MESSAGES, TRIM_S, TRIM_BUSY_S, trim=lambda: give_back_now())
        self.refused_large = False  # a raw payload over a raw message's size was refused this step (a bomb: MBs)
        self.guard = Guard("dashboard", log, state.dropped)

    def _alive(self) -> Subscriber:
        """The devices' tokens (those alive now first: history), on a new session of their own with an opener."""
        stack, session = contextlib.ExitStack(), self.session
        if self.opener is not None:
            session = stack.enter_context(self.opener())
        channel: zenoh.handlers.FifoChannel[zenoh.Sample] = zenoh.handlers.FifoChannel(CHANNEL_CAPACITY)
        key = wire.liveliness_key(self.prefix, "device", "*")
        subscriber = stack.enter_context(session.liveliness().declare_subscriber(key, channel, history=True))
        self.alive_declared = stack
        return subscriber

    def _renew_alive(self) -> None:
        """The tokens on a new session (its history gives the live ones again), the old one's samples taken, then
        the old closed: what Zenoh kept for every token key it was told of goes with it."""
        old, old_declared = self.alive, self.alive_declared
        self.alive = self._alive()
        for sample in drain(old, MAX_DRAIN):
            self.guard.run("alive", self._on_alive, sample)
        old_declared.close()
        self.tokens_seen = self.tokens_alive = 0
        self.renewed += 1
        log.info("a new session for the devices' liveliness tokens (%d renewals)", self.renewed)

    def _declare(self, subscriber: Subscriber) -> Subscriber:
        return self.declared.enter_context(subscriber)

    def _subscribe(
        self,
        kind: wire.Kind,
        channel: zenoh.handlers.FifoChannel[zenoh.Sample] | zenoh.handlers.RingChannel[zenoh.Sample],
    ) -> Subscriber:
        return self._declare(self.session.declare_subscriber(wire.key(self.prefix, "*", kind), channel))

    def __enter__(self) -> Ingest:
        return self

    def __exit__(self, *exc: object) -> None:
        for _, watch in self.raw_watched.values():
            watch.close()
        self.raw_watched.clear()
        self.declared.close()
        self.alive_declared.close()

    def run(self) -> None:
        """Drain until ``stop`` is set."""
        while not self.stop.is_set():
            started = time.monotonic()
            self.guard.run("ingest", self.step)  # nothing from the network ends the service
            self.stop.wait(max(0.0, self.tick_s - (time.monotonic() - started)))

    def step(self) -> None:
        self.state.forget_silent()
        self._follow_watched()
        self._ask_calibrations()
        run = self.guard.run  # each message through the guard: one that makes a handler fail is dropped, counted
        for sample in drain(self.alive, MAX_DRAIN):
            run("alive", self._on_alive, sample)
            self.tokens_seen += 1
            self.tokens_alive += 1 if sample.kind == zenoh.SampleKind.PUT else -1
        if self.opener is not None and self.tokens_seen >= TOKENS_PER_SESSION + 2 * self.tokens_alive:
            self._renew_alive()
        for sample in drain(self.calibrations, MAX_DRAIN):
            run("calibration", self._on_calibration, str(sample.key_expr), payload_bytes(sample))
        self._take_replies()
        for sample in drain(self.alerts, MAX_DRAIN):
            run("alert", self._on_alert, str(sample.key_expr), payload_bytes(sample))
        progress = copied(self.progress, MAX_DRAIN)
        taken = len(progress)
        for key_expr, payload in progress:
            run("progress", self._on_progress, key_expr, payload)
        del progress
        self._take_raws(self.raw_any, True)
        for subscriber, _ in list(self.raw_watched.values()):
            self._take_raws(subscriber, False)
        headings = copied(self.headings, MAX_DRAIN)
        taken += len(headings)
        run("heading", self._on_headings, headings, count=len(headings))
        self.trim.after_step(taken, burst=self.refused_large)
        self.refused_large = False
        if self.metrics_board is not None and self.metrics_board.due():
            self.metrics_board.write(self.state.metrics_status())

    # ---------------------------------------------------------------------------------------------- messages
    def _drop(self, exc: wire.WireError, what: str) -> None:
        self.state.dropped.drop(exc, what, log)

    def _device(self, key_expr: str, kind: wire.Kind) -> str | None:
        try:
            return wire.device_from_key(self.prefix, key_expr, kind)
        except wire.WireError as exc:
            self._drop(exc, kind.value)
            return None

    def _on_alive(self, sample: zenoh.Sample) -> None:
        name = str(sample.key_expr).rsplit("/", 1)[-1]
        try:
            wire.validate_device_id(name)
        except ValueError:
            return
        self.state.on_alive(name, sample.kind == zenoh.SampleKind.PUT)

    def _on_calibration(self, key_expr: str, payload: bytes) -> None:
        try:
            message = wire.decode_calibration(payload)
            wire.check_key(self.prefix, key_expr, wire.Kind.CALIBRATION, message.device)
        except wire.WireError as exc:
            self._drop(exc, "calibration")
            return
        self.state.on_calibration(message)

    def _on_alert(self, key_expr: str, payload: bytes) -> None:
        """A drift alert raised or cleared by a compass (or an open one it answered); malformed ones dropped."""
        try:
            message = wire.unpack(payload)
            wire.check_key(self.prefix, key_expr, wire.Kind.ALERT, wire.message_device(message))
            alert = alert_from_message(message)
        except wire.WireError as exc:
            self._drop(exc, "alert")
            return
        except ValueError as exc:
            self._drop(wire.WireError("bad-alert", str(exc)), "alert")
            return
        self.state.on_alert(alert)

    def _on_progress(self, key_expr: str, payload: bytes) -> None:
        try:
            message = wire.decode_progress(payload)
            wire.check_key(self.prefix, key_expr, wire.Kind.PROGRESS, message["device"])
        except wire.WireError as exc:
            self._drop(exc, "progress")
            return
        self.state.on_progress(message)

    def _take_raws(self, handler: Receiver[zenoh.Sample], only_new: bool) -> None:
        """The raw samples ``handler`` holds now, each handled and let go before the next is taken (a sample holds
        its receive buffer: a drain of bombs held at once was 4 MB each, plus a copy of each)."""
        for _ in range(MAX_DRAIN):
            try:
                sample = handler.try_recv()
            except zenoh.ZError:
                return
            if sample is None:
                return
            self.guard.run("raw", self._on_raw, sample, only_new)
            del sample

    def _on_raw(self, sample: zenoh.Sample, only_new: bool) -> None:
        key_expr = str(sample.key_expr)
        device = self._device(key_expr, wire.Kind.RAW)
        if device is None or (only_new and (device in self.raw_watched or self._has_sensor(device))):
            return
        size = len(sample.payload)
        if size > wire.RAW_LIMITS.payload_bytes:  # refused before it is copied out of Zenoh (as the compass does)
            self._drop(wire.WireError("oversized", f"{size} bytes, more than a raw message may be"), "raw")
            self.refused_large = True  # Zenoh reassembled its MBs in the heap: given back as after a burst
            return
        try:
            batch = wire.decode_raw(payload_bytes(sample))
            wire.check_key(self.prefix, key_expr, wire.Kind.RAW, batch.device)
        except wire.WireError as exc:
            self._drop(exc, "raw")
            return
        self.state.on_sensor(batch.device, batch.sensor)
        if not only_new:
            self.state.on_raw(batch)

    def _has_sensor(self, device: str) -> bool:
        row = self.state.rows.get(device)
        return row is not None and bool(row.sensor)

    def _on_headings(self, messages: list[tuple[str, bytes]]) -> None:
        """Decode the newest message of each device, and every message of a watched device, in arrival order
        (``messages``: (key, payload), emptied here)."""
        latest: dict[str, bytes] = {}
        chosen: list[tuple[str, bytes]] = []
        for key_expr, payload in messages:
            if key_expr.rsplit("/", 2)[-2] in self.raw_watched:
                chosen.append((key_expr, payload))
            else:
                latest[key_expr] = payload
        self.state.messages += len(messages)
        messages.clear()
        for key_expr, payload in chosen + list(latest.items()):
            self._on_heading(key_expr, payload)

    def _on_heading(self, key_expr: str, payload: bytes) -> None:
        try:
            batch = wire.decode_heading(payload)
            wire.check_key(self.prefix, key_expr, wire.Kind.HEADING, batch.device)
        except wire.WireError as exc:
            self._drop(exc, "heading")
            return
        if len(batch):
            metrics.observe_latency((time.time_ns() - int(batch.t_ns[-1])) / 1e9)
        self.state.on_heading(batch)

    # ---------------------------------------------------------------------------------------------- upkeep
    def _follow_watched(self) -> None:
        """A raw subscriber of its own for each device someone looks at (each in its own ExitStack, closed when
        nobody looks any more)."""
        watched = self.state.watched()
        for device in set(self.raw_watched) - watched:
            self.raw_watched.pop(device)[1].close()
        for device in watched - set(self.raw_watched):
            with contextlib.ExitStack() as watch:
                subscriber = watch.enter_context(
                    self.session.declare_subscriber(
                        wire.key(self.prefix, device, wire.Kind.RAW), zenoh.handlers.FifoChannel(CHANNEL_CAPACITY)
                    )
                )
                self.raw_watched[device] = (subscriber, watch.pop_all())

    def _ask_calibrations(self) -> None:
        """Ask for every calibration in force and every open drift alert at start, and again now and then (a
        calibrator or compass that came later)."""
        now = time.monotonic()
        if now - self.asked_s < REQUERY_S:
            return
        self.asked_s = now
        for kind in (wire.Kind.CALIBRATION, wire.Kind.ALERT):
            # no consolidation: a device's open alerts of several kinds share its key, and Zenoh would keep only one
            asked = self.session.get(
                wire.key(self.prefix, "*", kind), timeout=3.0, consolidation=zenoh.ConsolidationMode.NONE
            )
            self.pending.append((now + 3.0, asked))

    def _take_replies(self) -> None:
        still = []
        for deadline, handler in self.pending:
            for reply in drain(handler, 100_000):
                if reply.ok is None:
                    continue
                key_expr = str(reply.ok.key_expr)
                if key_expr.endswith("/" + wire.Kind.ALERT.value):
                    self.guard.run("alert", self._on_alert, key_expr, payload_bytes(reply.ok))
                else:
                    self.guard.run("calibration", self._on_calibration, key_expr, payload_bytes(reply.ok))
            if time.monotonic() < deadline:
                still.append((deadline, handler))
        self.pending = still


class Control:
    """The queries behind the page's buttons and history: the same queryables ``magnet calibrate`` and
    ``magnet get calibration --history`` use. Blocking (call from a worker thread)."""

    def __init__(self, session: zenoh.Session, prefix: str) -> None:
        self.session, self.prefix = session, prefix

    def _ask(self, selector: str) -> tuple[list[dict[str, Any]], list[str]]:
        answers, errors = [], []
        for reply in self.session.get(selector, timeout=QUERY_TIMEOUT_S):
            if reply.ok is not None:
                try:
                    answers.append(wire.unpack(payload_bytes(reply.ok)))
                except wire.WireError as exc:
                    errors.append(str(exc))
            elif reply.err is not None:
                errors.append(payload_bytes(reply.err).decode(errors="replace"))
        return answers, errors

    def calibrate(
        self, device: str, action: str, method: str | None, to: str | None = None, by: str | None = None
    ) -> tuple[list[dict[str, Any]], list[str]]:
        params = f"action={action}" + (f";method={method}" if method else "")
        params += (f";to={to}" if to else "") + (f";by={by}" if by else "")
        return self._ask(f"{wire.key(self.prefix, device, wire.Kind.CALIBRATE)}?{params}")

    def history(self, device: str, limit: int) -> tuple[list[dict[str, Any]], list[str]]:
        return self._ask(f"{wire.key(self.prefix, device, wire.Kind.HISTORY)}?limit={limit}")

    def vehicles(self) -> tuple[list[dict[str, Any]], list[str]]:
        """Every vehicle's compasses compared, as the compasses answer (docs/vehicles.md)."""
        return self._ask(wire.vehicle_key(self.prefix, "*"))
