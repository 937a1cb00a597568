"""``magnet calibrator``: collect raw samples per device, fit, gate, store (SQLite) and serve calibrations.

Collection (``magnet.collection``) keeps samples evenly spread over the sphere (bounded by ``--max-samples``).
Without a session, a device that has no calibration is fitted whenever enough new cells filled and coverage reached
``--min-coverage``; the first fit the quality gate accepts is stored and published, and collection for it ends. An
operator's session (``calibrate`` queryable: start / status / commit / abort) collects afresh with its method and
stores only on commit. A rejected fit changes nothing: its reason goes out on ``calibration/progress``.

Queryables: see ``services.calibrator.queries``. One thread: zenoh delivers into channels, this loop drains them.
The options and settings are in ``services.calibrator.settings``, the core (no zenoh) in ``services.calibrator.core``
and the operator sessions in ``services.calibrator.sessions``.
"""

from __future__ import annotations

import argparse
import logging
import time
from collections.abc import Callable, Sequence
from typing import Any

import zenoh

from magnet import wire
from services.calibrator import queries
from services.calibrator.core import Calibrator, CalibratorStatus, Counters, State
from services.calibrator.fleet import FleetBook
from services.calibrator.sessions import ACTIONS
from services.calibrator.settings import (
    DEFAULT_MAX_DEVICES,
    CalibratorSettings,
    ServiceSettings,
    add_arguments,
    default_db_path,
    load_signer,
    settings_from_args,
)
from services.calibrator.store import CalibrationStore
from services.common.zenoh_session import drain, open_session, payload_bytes, stop_event

__all__ = [
    "ACTIONS",
    "DEFAULT_MAX_DEVICES",
    "Calibrator",
    "CalibratorSettings",
    "CalibratorStatus",
    "Counters",
    "ServiceSettings",
    "State",
    "add_arguments",
    "default_db_path",
    "run",
    "run_calibrator",
    "settings_from_args",
]

log = logging.getLogger("magnet.calibrator")

CHANNEL_CAPACITY = 65536
IDLE_SLEEP_S = 0.0005

# ------------------------------------------------------------------------------------------------------- shell


def run_calibrator(args: argparse.Namespace) -> int:
    """``magnet calibrator``: the settings from the options, then ``run``."""
    return run(settings_from_args(args))


def run(settings: ServiceSettings) -> int:
    stop = stop_event()
    prefix, devices, name = settings.zenoh.prefix, settings.devices, settings.name
    signer = load_signer(settings.signing_key)  # a bad key file ends here, before anything is opened
    with CalibrationStore(settings.db) as store, open_session(settings.zenoh) as session:

        def publish(kind: wire.Kind, device: str, payload: bytes) -> None:
            # no declared publisher per device: a flood of new device ids would hold one each
            session.put(wire.key(prefix, device, kind), payload)

        calibrator = Calibrator(
            store, settings.fitting, publish, signer=signer, fleet=FleetBook(settings.places), shard=settings.shard
        )
        token = session.liveliness().declare_token(wire.liveliness_key(prefix, "calibrator", name))
        raw_sub = session.declare_subscriber(f"{prefix}/{devices}/raw", zenoh.handlers.FifoChannel(CHANNEL_CAPACITY))
        answers = [
            (
                queries.ANSWERS[kind],
                session.declare_queryable(f"{prefix}/{devices}/{kind.value}", zenoh.handlers.FifoChannel(256)),
            )
            for kind in queries.ANSWERS
        ]
        answers.append(
            (
                queries.status_answer(name),
                session.declare_queryable(wire.status_key(prefix, name), zenoh.handlers.FifoChannel(64)),
            )
        )
        answers.append(
            (queries.answer_fleet, session.declare_queryable(f"{prefix}/@fleet", zenoh.handlers.FifoChannel(16)))
        )
        alert_key = f"{prefix}/{devices}/{wire.Kind.ALERT.value}"
        feeds: list[tuple[Any, Callable[[str, bytes, str], None]]] = [
            (session.declare_subscriber(alert_key, zenoh.handlers.FifoChannel(4096)), calibrator.fleet.on_alert),
            (session.get(alert_key, timeout=3.0), calibrator.fleet.on_alert),
        ]  # the alerts open already
        for device, record in calibrator.in_force.items():
            publish(wire.Kind.CALIBRATION, device, wire.pack(record.to_record()))
        log.info(
            "calibrator %s (shard %s): %d calibration(s) in store %s",
            name,
            settings.shard,
            len(calibrator.in_force),
            store.path,
        )
        _loop(stop, calibrator, raw_sub, answers, prefix, feeds)
        token.undeclare()
    log.info("calibrator stopped: %s", calibrator.status(name).to_dict())
    return 0


def _loop(
    stop: Any,
    calibrator: Calibrator,
    raw_sub: Any,
    answers: list[tuple[Any, Any]],
    prefix: str,
    feeds: Sequence[tuple[Any, Callable[[str, bytes, str], None]]] = (),
) -> None:
    """Drain raw samples, queries and ``feeds`` (samples or replies -> handler(key, payload, prefix)) until
    ``stop`` is set."""
    while not stop.is_set():
        for handler, take in feeds:
            for item in drain(handler, 1000):
                sample = getattr(item, "ok", item)
                if sample is not None and hasattr(sample, "key_expr"):
                    take(str(sample.key_expr), payload_bytes(sample), prefix)
        samples = drain(raw_sub, 2000)
        for sample in samples:
            calibrator.on_raw(str(sample.key_expr), payload_bytes(sample), prefix)
        for answer, queryable in answers:
            for query in drain(queryable, 64):
                answer(query, calibrator, prefix)
                query.drop()  # finalize now: the asker waits for it
        if not samples:
            time.sleep(IDLE_SLEEP_S)
