"""Issue 32: the calibrator answered its status between chunks of its loop (a 10-minute soak: 226 of 227 within 1 s,
the missed one after a flood). It is now answered from Zenoh's thread with what the loop last wrote, as the
compass's is (``services.common.status_board``): a query asked while the loop is stuck inside a handler is answered
at once, with the age of what it says; the loop writes its status at most every ``STATUS_REFRESH_S``."""

from __future__ import annotations

import threading
from contextlib import ExitStack
from pathlib import Path
from typing import Any

import numpy as np
from helpers import StatusQuery as Query

from magnet import wire
from services.calibrator.intake import RawIntake
from services.calibrator.service import STATUS_REFRESH_S, Calibrator, CalibratorSettings, ServiceLoop, _declare_answers
from services.calibrator.store import CalibrationStore

PREFIX = wire.DEFAULT_PREFIX


class Channel:
    def try_recv(self) -> None:
        return None

    def __enter__(self) -> Channel:
        return self

    def __exit__(self, *exc: object) -> None:
        pass


class Session:
    def declare_queryable(self, key: str, handler: Any) -> Channel:
        return Channel()


def raw(device: str) -> bytes:
    mag, acc = np.random.default_rng(0).normal(size=(10, 3)) * 40, np.tile([0.0, 0.0, -9.8], (10, 1))
    return wire.encode_raw(wire.RawBatch(device, 0, "sim", np.arange(10), mag, acc))


def service_loop(store: CalibrationStore) -> ServiceLoop:
    calibrator = Calibrator(store, CalibratorSettings(), lambda *a: None)
    answers = _declare_answers(ExitStack(), Session(), PREFIX, "*", "cal")  # type: ignore[arg-type]
    assert "query:status" not in [what for what, _, _ in answers]  # the loop drains no status queries
    return ServiceLoop(calibrator, RawIntake(100), answers, PREFIX, name="cal")


def ask(loop: ServiceLoop) -> Query:
    query = Query()
    loop.board.answer(query)  # as Zenoh's thread does
    assert query.dropped and query.errors == [], query.errors
    return query


def test_status_is_answered_while_the_loop_is_stuck_in_a_handler(tmp_path: Path) -> None:
    with CalibrationStore(tmp_path / "c.db") as store:
        loop = service_loop(store)
        inside, release = threading.Event(), threading.Event()

        def stuck(key: str, payload: bytes, prefix: str) -> None:
            inside.set()
            release.wait(30)  # a handler that takes as long as the test likes

        loop.calibrator.on_raw = stuck  # type: ignore[method-assign]
        loop.intake.offer(f"{PREFIX}/d1/raw", raw("d1"))
        worker = threading.Thread(target=loop.step)
        worker.start()
        try:
            assert inside.wait(10)
            [(key, status)] = ask(loop).replies  # while the loop is in its handler
            assert key == f"{PREFIX}/@status/cal" and status["service"] == "calibrator" and status["name"] == "cal"
            assert status["status_age_s"] >= 0.0 and status["store"] == "ok"
        finally:
            release.set()
            worker.join(10)
        assert not worker.is_alive()


def test_the_loop_writes_its_status_at_most_every_refresh_period(tmp_path: Path) -> None:
    with CalibrationStore(tmp_path / "c.db") as store:
        loop = service_loop(store)
        now = [0.0]
        loop.board.clock = lambda: now[0]
        loop.board.write(loop.calibrator.status("cal").to_dict())
        loop.intake.offer(f"{PREFIX}/d1/raw", raw("d1"))
        loop.step()  # the batch taken, the status not yet due
        assert loop.calibrator.collections.received_batches == 1
        assert ask(loop).replies[0][1]["received_batches"] == 0
        now[0] += STATUS_REFRESH_S
        loop.step()
        now[0] += 1.5
        status = ask(loop).replies[0][1]
        assert status["received_batches"] == 1 and status["raw_messages"] == 1 and status["status_age_s"] == 1.5
        loop.board.latest = None  # nothing written yet: an error the asker can act on, not a silence
        starting = Query()
        loop.board.answer(starting)
        assert starting.replies == [] and b"calibrator is starting" in starting.errors[0] and starting.dropped


class Tokens:
    """A liveliness subscriber holding the given token samples (PUT: appeared)."""

    def __init__(self, *keys: str) -> None:
        import zenoh

        self.samples = [type("Token", (), {"key_expr": key, "kind": zenoh.SampleKind.PUT})() for key in keys]

    def try_recv(self) -> Any:
        return self.samples.pop(0) if self.samples else None


def test_a_lease_that_moves_is_on_the_board_at_once_not_a_refresh_later(tmp_path: Path) -> None:
    """The secure deployment's standby test asked a second calibrator within the refresh after it stood by and read
    'active' (its history of lease tokens came after its start): a moved lease is written at once."""
    from magnet.shard import Shard
    from services.calibrator.lease import Lease, Member, lease_prefix

    with CalibrationStore(tmp_path / "c.db") as store:
        loop = service_loop(store)
        now = [0.0]
        loop.board.clock = lambda: now[0]
        shard = Shard(0, 1)
        lease = Lease(PREFIX, shard, Member(2_000, "cal"))
        older = f"{lease_prefix(PREFIX, shard)}/1000/cal-0"
        loop.lease_watch = (Tokens(older), lease)  # type: ignore[assignment]
        loop.board.write(loop.calibrator.status("cal").to_dict())
        assert ask(loop).replies[0][1]["lease"] == "active"
        loop.step()  # the older calibrator's token arrives: this one stands by, well within the refresh period
        assert not loop.calibrator.active
        assert ask(loop).replies[0][1]["lease"] == "standby"


def test_metrics_read_the_board_and_never_the_calibrator_itself(tmp_path: Path) -> None:
    """Issue 32: ``--metrics`` built the calibrator's status on the metrics server's thread (the calibrator's state
    read beside the loop that changes it). What it serves now is the board's: what the loop last wrote, the alerts
    open by kind with it, and how old it is."""
    from magnet.drift import Alert, AlertKind
    from services.common.metrics import families

    with CalibrationStore(tmp_path / "c.db") as store:
        loop = service_loop(store)
        now = [0.0]
        loop.board.clock = lambda: now[0]
        alert = Alert("d1", AlertKind.FIELD_STRENGTH, 1, 60.0, 50.0, "recalibrate")
        loop.calibrator.roster.on_alert(f"{PREFIX}/d1/alert", wire.pack(alert.to_message()), PREFIX)
        loop.write_status()
        asked: list[str] = []
        loop.calibrator.status = lambda name: asked.append(name)  # type: ignore[assignment,method-assign,return-value]
        now[0] += 0.7
        status = loop.board.read()
        assert asked == []  # read without touching the calibrator
        assert status["service"] == "calibrator" and status["status_age_s"] == 0.7
        assert status["alerts_open"] == {AlertKind.FIELD_STRENGTH.value: 1}
        names = {family.name for family in families("calibrator", status)}
        assert {"magnet_dropped", "magnet_devices", "magnet_alerts_open"} <= names
        assert ask(loop).replies[0][1] == status  # the same as the status queryable answers
