"""``magnet calibrator``: collect raw samples per device, fit, gate, store (a SQLite file or a PostgreSQL database:
``--db``, ``services.common.stores``) and serve calibrations.

Collection (``magnet.calibration.collection``) keeps samples evenly spread over the sphere (bounded by
``--max-samples``). Without a session, a device that has no calibration is fitted whenever enough new cells filled and
coverage reached ``--min-coverage``; the first fit the quality gate accepts is stored and published, and collection for
it ends. An operator's session (``calibrate`` queryable: start / status / commit / abort) collects afresh with its
method and stores only on commit. A rejected fit changes nothing: its reason goes out on ``calibration/progress``.

Several calibrators may serve one shard: the oldest running holds the lease and alone collects, stores and answers;
the others stand by and take over when its liveliness token goes away (``services.calibrator.lease``).

Queryables: see ``services.calibrator.queries``. One thread does the work: a pump thread only moves raw messages
from Zenoh into a bounded queue (drops counted: ``services.calibrator.intake``), and this loop answers queries
between slices of samples; every handler runs through ``services.common.guard``, so nothing ends it; the status is
answered from Zenoh's thread (behind a router on a session of its own), and read by ``--metrics``, from the board.
The options and settings are in ``services.calibrator.settings``; the calibrator's decisions, without zenoh, a
database or a clock of their own, are ``magnet.calibrator.CalibratorCore``, which ``Calibrator`` gives the clocks
(docs/calibrator.md).
"""

from __future__ import annotations

import argparse
import logging
import threading
import time
from collections.abc import Callable, Sequence
from contextlib import ExitStack

import zenoh
from zenoh.handlers import FifoChannel, Handler

from magnet import signing, wire
from magnet.calibrator.core import CalibratorCore, Publish
from magnet.calibrator.roster import Roster
from magnet.calibrator.status import CalibratorStatus, IntakeFigures, State
from magnet.calibrator.store import CalibrationStore as Store
from magnet.shard import EVERY_DEVICE, Shard
from services.calibrator import queries
from services.calibrator.intake import Enrolment, RawIntake, new_device
from services.calibrator.lease import Lease, Member
from services.calibrator.settings import (
    DEFAULT_MAX_DEVICES,
    CalibratorSettings,
    ServiceSettings,
    add_arguments,
    default_db_path,
    load_signer,
    make_places,
    settings_from_args,
)
from services.calibrator.store import open_store
from services.common import metrics, zenoh_session
from services.common.guard import Guard
from services.common.status_board import StatusBoard
from services.common.zenoh_session import Receiver, drain, open_session, payload_bytes, queries_session, stop_event
from services.security.identities import certificate_identity, check_calibrator_identity

__all__ = [
    "DEFAULT_MAX_DEVICES",
    "Calibrator",
    "CalibratorSettings",
    "CalibratorStatus",
    "ServiceSettings",
    "State",
    "add_arguments",
    "default_db_path",
    "run",
    "run_calibrator",
    "settings_from_args",
]

log = logging.getLogger("magnet.calibrator")

IDLE_SLEEP_S = 0.0005
#: raw messages between Zenoh and the intake's pump (kept near empty by it; a burst of large messages waits in the
#: intake, bounded in bytes, not here)
CHANNEL_CAPACITY = 256
SLICE_S = 0.05  # raw samples taken for at most this long before the queries are answered again
STORE_CHECK_S = 1.0  # how often the loop looks whether its database file was deleted or replaced
SLICE_MESSAGES = 50  # raw messages taken from the intake at a time (the slice's end is checked between them)
ENROL_BURST_S = 10.0  # new device ids admitted at once after a quiet spell: this many seconds of --enrol-rate
LEASE_QUERY_S = 2.0  # how long it waits at start for the lease tokens of its shard
ALERT_QUERY_S = 3.0  # how long it waits at start for the alerts open already
STATUS_REFRESH_S = 0.2  # the status is written this often: 3.5 ms for 4,000 devices, 7 % of a core at 20/s

#: a queryable of the service: (what, for the drop counts; how to answer; the queryable)
Answering = tuple[str, queries.Answer, "zenoh.Queryable[Handler[zenoh.Query]]"]
#: samples (a subscriber's) or replies (a query's) and what takes each: handler(key, payload, prefix)
Feed = tuple["Receiver[zenoh.Sample | zenoh.Reply]", Callable[[str, bytes, str], None]]
#: the lease tokens of the shard, as they come and go, and the lease they move
LeaseWatch = tuple["zenoh.Subscriber[Handler[zenoh.Sample]]", Lease]

# ------------------------------------------------------------------------------------------------------- shell


class Calibrator(CalibratorCore):
    """``CalibratorCore`` on this process's clocks (monotonic s, wall clock ns) unless others are given."""

    def __init__(
        self,
        store: Store,
        settings: CalibratorSettings,
        publish: Publish,
        clock: Callable[[], float] = time.monotonic,
        clock_ns: Callable[[], int] = time.time_ns,
        signer: signing.Signer | None = None,
        roster: Roster | None = None,
        shard: Shard = EVERY_DEVICE,
    ) -> None:
        super().__init__(store, settings, publish, clock, clock_ns, signer, roster, shard)


def add_calibrator_arguments(parser: argparse.ArgumentParser) -> None:
    add_arguments(parser)
    metrics.add_metrics_argument(parser)


def run_calibrator(args: argparse.Namespace) -> int:
    """``magnet calibrator``: the settings from the options, then ``run``."""
    if getattr(args, "metrics", None):
        metrics.parse_address(args.metrics)  # a bad address ends here, before anything is opened
    return run(settings_from_args(args), getattr(args, "metrics", None))


def _publisher(session: zenoh.Session, prefix: str) -> Publish:
    def publish(kind: wire.Kind, device: str, payload: bytes) -> None:
        # no declared publisher per device: a flood of new device ids would hold one each
        session.put(wire.key(prefix, device, kind), payload)

    return publish


def run(settings: ServiceSettings, metrics_address: str | None = None) -> int:
    stop = stop_event()
    signer = load_signer(settings.signing_key)  # a bad key file ends here, before anything is opened
    identity = certificate_identity(settings.zenoh.config)  # a calibrator identity of another shard ends here too
    check_calibrator_identity(identity, settings.shard.index, settings.shard.count)
    lease = Lease(settings.zenoh.prefix, settings.shard, Member(time.time_ns(), settings.name))
    fitting = settings.fitting
    places = make_places(settings.fleet, fitting.location, fitting.max_devices)
    with (
        open_store(settings.db_path) as store,
        open_session(settings.zenoh) as session,
        ExitStack() as declared,  # every declaration, undeclared in reverse order before the session closes
    ):
        calibrator = Calibrator(
            store,
            fitting,
            _publisher(session, settings.zenoh.prefix),
            signer=signer,
            roster=Roster(places, fitting.max_devices),
            shard=settings.shard,
        )
        loop = _declare(declared, session, settings, calibrator, lease)
        metrics.start(metrics_address, "calibrator", loop.board.read)  # what the loop wrote, never its state
        if calibrator.active:
            calibrator.publish_in_force()
        log.info(
            "calibrator %s (shard %s, %s; %s holds the lease): %d calibration(s) in store %s",
            settings.name,
            settings.shard,
            lease.state(),
            lease.holder,
            len(calibrator.records.in_force),
            store.path,
        )
        _loop(stop, loop)
    log.info("calibrator stopped: %s", calibrator.status(settings.name).to_dict())
    return 0


def _declare(
    declared: ExitStack, session: zenoh.Session, settings: ServiceSettings, calibrator: Calibrator, lease: Lease
) -> ServiceLoop:
    """Declare everything the calibrator needs on ``session`` into ``declared``: its lease token, the raw subscriber
    and the pump thread that empties it, the queryables, the alerts, the status board's, then its liveliness token;
    the loop that serves them."""
    prefix, devices, name = settings.zenoh.prefix, settings.devices, settings.name
    lease_sub = _join_lease(declared, session, lease)
    calibrator.active = lease.active
    intake = RawIntake(settings.max_queue)
    raw_link = zenoh_session.raw_session(declared, session, settings.zenoh)  # behind a router: a link, 8 kB batches
    raw_sub = raw_link.declare_subscriber(f"{prefix}/{devices}/raw", FifoChannel(CHANNEL_CAPACITY))
    args = (raw_sub.handler, payload_bytes, zenoh.ZError)
    pump = threading.Thread(target=intake.pump, args=args, name="raw-intake", daemon=True)
    declared.callback(pump.join, 2.0)
    declared.enter_context(raw_sub)  # undeclared before the join above: that ends the pump
    pump.start()
    answers = _declare_answers(declared, session, prefix, devices, name)
    alert_key = f"{prefix}/{devices}/{wire.Kind.ALERT.value}"
    alert_sub = declared.enter_context(session.declare_subscriber(alert_key, FifoChannel(4096)))
    feeds: list[Feed] = [
        (alert_sub.handler, calibrator.roster.on_alert),
        (session.get(alert_key, timeout=ALERT_QUERY_S), calibrator.roster.on_alert),  # the alerts open already
    ]
    enrolment = Enrolment(settings.enrol_rate, max(1, int(settings.enrol_rate * ENROL_BURST_S)))
    loop = ServiceLoop(calibrator, intake, answers, prefix, feeds, (lease_sub, lease), enrolment, name)
    status_session = queries_session(declared, session, settings.zenoh)  # behind a router: a link of its own
    declared.enter_context(status_session.declare_queryable(loop.board.key, loop.board.answer))
    # the liveliness token last: who sees it (a compass asks for every record then) finds the queryables declared
    declared.enter_context(session.liveliness().declare_token(wire.liveliness_key(prefix, "calibrator", name)))
    return loop


def _join_lease(declared: ExitStack, session: zenoh.Session, lease: Lease) -> zenoh.Subscriber[Handler[zenoh.Sample]]:
    """Declare this calibrator's lease token and watch the others of its shard; the ones already there are read
    before it serves anything, so a calibrator that starts beside a running one stands by from the start."""
    declared.enter_context(session.liveliness().declare_token(lease.key))
    subscriber = declared.enter_context(
        session.liveliness().declare_subscriber(lease.watch_key, FifoChannel(256), history=True)
    )
    for reply in session.liveliness().get(lease.watch_key, timeout=LEASE_QUERY_S):
        if reply.ok is not None:
            lease.on_token(str(reply.ok.key_expr), True)
    return subscriber


def _follow_lease(subscriber: zenoh.Subscriber[Handler[zenoh.Sample]], lease: Lease, calibrator: Calibrator) -> None:
    """Tokens of the shard that appeared or went away: take over or stand by when the lease moved."""
    sample: zenoh.Sample
    for sample in drain(subscriber, 256):
        active = lease.on_token(str(sample.key_expr), sample.kind == zenoh.SampleKind.PUT)
        if active is True:
            calibrator.take_over()
        elif active is False:
            calibrator.stand_by()


def _declare_answers(
    declared: ExitStack, session: zenoh.Session, prefix: str, devices: str, name: str
) -> list[Answering]:
    """(what, handler, queryable) for every queryable the loop drains: the device kinds and the fleet."""
    asked = [
        (f"query:{kind.value}", queries.ANSWERS[kind], f"{prefix}/{devices}/{kind.value}", 256)
        for kind in queries.ANSWERS
    ]
    asked.append(("query:fleet", queries.FLEET_ANSWER, f"{prefix}/@fleet", 16))
    return [
        (what, answer, declared.enter_context(session.declare_queryable(key, FifoChannel(capacity))))
        for what, answer, key, capacity in asked
    ]


class ServiceLoop:
    """One round at a time (``step``): the lease tokens, the ``feeds`` (samples or replies -> handler(key, payload,
    prefix)), the queries, then raw samples from the intake for at most ``SLICE_S``, SLICE_MESSAGES at a time with
    the queries answered after each; every handler run through the guard (``services.common.guard``), so none ends
    the service. A flood of samples delays samples, not answers; the status (``board``) is answered without it."""

    def __init__(
        self,
        calibrator: Calibrator,
        intake: RawIntake,
        answers: Sequence[Answering],
        prefix: str,
        feeds: Sequence[Feed] = (),
        lease_watch: LeaseWatch | None = None,
        enrolment: Enrolment | None = None,
        name: str = "calibrator",
    ) -> None:
        self.calibrator, self.intake, self.answers, self.prefix = calibrator, intake, answers, prefix
        self.feeds, self.lease_watch, self._store_checked_s, self.name = feeds, lease_watch, 0.0, name
        self.enrolment = enrolment if enrolment is not None else Enrolment()
        self.guard = Guard("calibrator", log, calibrator.drops)
        self.board = StatusBoard(wire.status_key(prefix, name), self.guard, refresh_s=STATUS_REFRESH_S)
        self.write_status()

    def step(self) -> bool:
        """One round; True when raw samples were taken. Once every STORE_CHECK_S, whether the store's file is gone
        (logged once when it is: ``CalibrationStore.gone``), even when nothing is written or asked."""
        if (now_s := time.monotonic()) - self._store_checked_s >= STORE_CHECK_S:
            self._store_checked_s = now_s
            self.guard.run("store", self.calibrator.store_gone)
        if self.lease_watch is not None:
            was_active = self.calibrator.active
            self.guard.run("lease", _follow_lease, *self.lease_watch, self.calibrator)
            if self.calibrator.active != was_active:  # a moved lease is on the board at once, not a refresh later
                self.write_status()
        for handler, take in self.feeds:
            for item in drain(handler, 1000):
                sample = item.ok if isinstance(item, zenoh.Reply) else item
                if sample is not None and hasattr(sample, "key_expr"):
                    self.guard.run("alert", take, str(sample.key_expr), payload_bytes(sample), self.prefix)
        self.answer_queries()
        return self.samples()

    def write_status(self) -> None:
        """The status on the board, which Zenoh's thread answers and ``--metrics`` reads: never the state itself."""
        self.board.write(queries.board_status(self.calibrator, self.name))

    def answer_queries(self) -> None:
        self._counters()
        if self.board.due():  # the status, answered from Zenoh's thread
            self.write_status()
        for what, answer, queryable in self.answers:
            query: zenoh.Query
            for query in drain(queryable, 64):
                self.guard.answer(what, query, answer, self.calibrator, self.prefix)
                query.drop()  # finalize now: the asker waits for it

    def samples(self) -> bool:
        """Raw samples from the intake for at most SLICE_S; True when there were any."""
        deadline = time.monotonic() + SLICE_S
        took = False
        while time.monotonic() < deadline:
            items = self.intake.take(SLICE_MESSAGES)
            if not items:
                break
            took = True
            for key_expr, payload in items:
                if self.admit(key_expr):
                    self.guard.run("raw", self.calibrator.on_raw, key_expr, payload, self.prefix)
            self.answer_queries()  # a query waits for one chunk of samples at most
        return took

    def admit(self, key_expr: str) -> bool:
        """False (counted ``raw:enrol-rate``) for a new device id beyond the enrolment rate."""
        calibrator = self.calibrator
        if (
            not calibrator.active
            or not calibrator.settings.auto
            or not new_device(key_expr, self.prefix, calibrator.known)
        ):
            return True
        if self.enrolment.admit():
            return True
        if calibrator.drops.count("raw:enrol-rate"):
            log.warning(
                "more than %g new device ids a second: the excess dropped (counted in status dropped[raw:enrol-rate];"
                " raise --enrol-rate if they are genuine)",
                self.enrolment.rate_per_s,
            )
        return False

    def _counters(self) -> None:
        """The intake's figures into the calibrator's status."""
        intake, admitted = self.intake, self.enrolment.admitted
        self.calibrator.intake = IntakeFigures(intake.raw_messages, len(intake), intake.high_water, admitted)
        for cause, count in (("raw:queue-full", intake.queue_full), ("raw:oversized", intake.oversized)):
            if count:
                self.calibrator.drops.counts[cause] = count


def _loop(stop: threading.Event, loop: ServiceLoop) -> None:
    """``loop.step()`` until ``stop`` is set, resting briefly when no samples came."""
    while not stop.is_set():
        if not loop.step():
            time.sleep(IDLE_SLEEP_S)
