"""No handler ends a service: for each kind of handler (calibrator queryables and raw subscriber, compass
subscribers and queryables, the edge's status queryable, the dashboard's ingest and HTTP routes) a failure is
injected (a store that cannot be written or read, a message that fails to decode, a bug) and the service answers
the next request. No network: the handlers are called through the same loop functions the services run, with fake
queries and channels."""

from __future__ import annotations

import logging
import sqlite3
import warnings
from contextlib import ExitStack
from typing import Any

import numpy as np
import pytest
from compass_steps import compass_core

from magnet import wire
from magnet.earth.expected import Earth
from magnet.model import Calibration
from services.calibrator.intake import Enrolment, RawIntake
from services.calibrator.service import Calibrator, CalibratorSettings, ServiceLoop, _declare_answers
from services.calibrator.store import CalibrationStore, StoreError
from services.common.guard import Guard, refusal
from services.dashboard.app import create_app
from services.dashboard.state import FleetState

with warnings.catch_warnings():  # starlette >= 1 asks for httpx2, which the package index does not have
    warnings.filterwarnings("ignore", message=".*httpx.*")
    from starlette.testclient import TestClient

PREFIX = "magnet"


class FakeQuery:
    def __init__(self, key_expr: str, **parameters: str) -> None:
        self.key_expr, self.parameters = key_expr, parameters
        self.replies: list[tuple[str, Any]] = []
        self.errors: list[str] = []
        self.dropped = False

    def reply(self, key: str, payload: bytes) -> None:
        self.replies.append((key, wire.unpack(payload)))

    def reply_err(self, payload: bytes) -> None:
        self.errors.append(payload.decode())

    def drop(self) -> None:
        self.dropped = True


class FakeChannel:
    """What ``drain`` reads: ``try_recv`` gives the queued items, then None."""

    def __init__(self) -> None:
        self.items: list[Any] = []

    def try_recv(self) -> Any:
        return self.items.pop(0) if self.items else None

    def __enter__(self) -> FakeChannel:
        return self

    def __exit__(self, *exc: object) -> None:
        self.items.clear()


class FakeSession:
    def declare_queryable(self, key: str, handler: Any) -> FakeChannel:
        return FakeChannel()


def _record(device: str, n: int) -> wire.DeviceCalibration:
    # a long reason: the record needs pages of its own, so a store that cannot grow cannot take it
    return wire.DeviceCalibration(device, n, Calibration("ellipsoid", [float(n), 0, 0], np.eye(3), reason="r" * 6000))


@pytest.fixture
def calibrator(tmp_path):
    with CalibrationStore(tmp_path / "c.db") as store:
        store.save(_record("d1", 1))
        store.save(_record("d1", 2))
        yield Calibrator(store, CalibratorSettings(), lambda *a: None, clock_ns=lambda: 99)


def _service(calibrator: Calibrator) -> tuple[ServiceLoop, dict[str, FakeChannel]]:
    answers = _declare_answers(ExitStack(), FakeSession(), PREFIX, "*", "cal")
    loop = ServiceLoop(calibrator, RawIntake(100), answers, PREFIX, enrolment=Enrolment(1000, 10), name="cal")
    return loop, {what: queryable for what, _, queryable in answers}


def _ask(loop: ServiceLoop, channels: dict[str, FakeChannel], what: str, query: FakeQuery) -> FakeQuery:
    channels[what].items.append(query)
    loop.step()
    assert query.dropped  # finalized: the asker is not left waiting
    return query


def _status(loop: ServiceLoop, channels: dict[str, FakeChannel]) -> dict[str, Any]:
    """The status as Zenoh's thread answers it (``loop.board``), as the loop wrote it in its next step."""
    loop.board.latest = None  # due now (the loop writes it every STATUS_REFRESH_S)
    loop.step()
    query = FakeQuery(f"{PREFIX}/@status/cal")
    loop.board.answer(query)
    assert query.dropped and len(query.replies) == 1, query.errors
    assert query.replies[0][0] == f"{PREFIX}/@status/cal"
    return query.replies[0][1]


def _refusals(query: FakeQuery) -> list[str]:
    """What the asker was told when its request was refused: an error reply (the guard), or an answer with ok false
    and its message (the rollback's own refusal)."""
    return [*query.errors, *(r["message"] for _, r in query.replies if not r.get("ok", True))]


def _fill_disk(store: CalibrationStore) -> None:
    """The database cannot grow by a page any more: sqlite's own 'database or disk is full' (SQLITE_FULL)."""
    pages = store._db.execute("PRAGMA page_count").fetchone()[0]
    store._db.execute(f"PRAGMA max_page_count = {pages}")


def test_rollback_on_a_full_disk_is_refused_clearly_and_the_calibrator_keeps_answering(calibrator):
    loop, channels = _service(calibrator)
    before = calibrator.records.in_force["d1"].id
    _fill_disk(calibrator.records.store)
    query = _ask(loop, channels, "query:calibrate", FakeQuery(f"{PREFIX}/d1/calibrate", action="rollback"))
    (said,) = _refusals(query)
    assert "the calibrator could not write its database" in said and "disk full" in said
    assert "restore it from a backup" not in said  # not called damaged
    assert calibrator.records.in_force["d1"].id == before  # nothing changed
    assert _status(loop, channels)["received_batches"] == 0  # and it keeps answering
    calibrator.records.store._db.execute("PRAGMA max_page_count = 1000000")  # space again: the same request now works
    query = _ask(loop, channels, "query:calibrate", FakeQuery(f"{PREFIX}/d1/calibrate", action="rollback"))
    assert query.replies and query.replies[0][1]["ok"], query.errors
    assert calibrator.records.in_force["d1"].calibration.offset[0] == 1.0


def test_rollback_whose_history_read_fails_is_refused_and_the_calibrator_keeps_answering(calibrator, monkeypatch):
    loop, channels = _service(calibrator)

    def unreadable(*args: Any, **kwargs: Any) -> None:
        exc = sqlite3.OperationalError("disk I/O error")
        exc.sqlite_errorcode = 10  # SQLITE_IOERR, as sqlite3 sets it
        with calibrator.records.store._guard("read"):
            raise exc

    monkeypatch.setattr(calibrator.records.store, "history", unreadable)
    query = _ask(loop, channels, "query:calibrate", FakeQuery(f"{PREFIX}/d1/calibrate", action="rollback"))
    (said,) = _refusals(query)
    assert "could not read its database" in said
    monkeypatch.undo()
    assert _status(loop, channels)["received_batches"] == 0
    query = _ask(loop, channels, "query:calibration", FakeQuery(f"{PREFIX}/d1/calibration"))
    assert [key for key, _ in query.replies] == [f"{PREFIX}/d1/calibration"]


def test_a_bug_in_a_query_handler_is_an_error_reply_and_the_next_query_is_answered(calibrator, monkeypatch):
    loop, channels = _service(calibrator)
    monkeypatch.setattr("services.calibrator.queries.roster_reply", lambda *a: 1 / 0)
    query = _ask(loop, channels, "query:fleet", FakeQuery(f"{PREFIX}/@fleet"))
    assert len(query.errors) == 1 and "ZeroDivisionError" in query.errors[0] and "keeps serving" in query.errors[0]
    monkeypatch.undo()
    query = _ask(loop, channels, "query:fleet", FakeQuery(f"{PREFIX}/@fleet"))
    assert query.replies and query.replies[0][1]["count"] == 1


def _raw(device: str, seq: int = 0) -> bytes:
    rng = np.random.default_rng(seq)
    mag, acc = rng.normal(size=(10, 3)) * 40, np.tile([0, 0, -9.8], (10, 1))
    batch = wire.RawBatch(device, seq, "sim", np.arange(10), mag, acc)
    return wire.encode_raw(batch)


def test_raw_messages_that_fail_to_decode_or_hit_a_bug_are_dropped_counted_and_the_next_is_processed(
    calibrator, monkeypatch, caplog
):
    loop, channels = _service(calibrator)
    calls = {"n": 0}
    on_raw = calibrator.on_raw

    def buggy(key: str, payload: bytes, prefix: str) -> None:
        calls["n"] += 1
        if calls["n"] == 2:
            raise RuntimeError("a bug")
        on_raw(key, payload, prefix)

    monkeypatch.setattr(calibrator, "on_raw", buggy)
    for key, payload in [("d2", _raw("d2")), ("d3", _raw("d3")), ("d4", b"\x93\x01"), ("d5", _raw("d5"))]:
        loop.intake.offer(f"{PREFIX}/{key}/raw", payload)
    with caplog.at_level(logging.ERROR, "magnet.calibrator"):
        loop.step()
    status = _status(loop, channels)
    assert status["received_batches"] == 2  # d2 and d5
    assert status["dropped"]["raw:handler-RuntimeError"] == 1
    assert sum(status["dropped"].values()) == 2  # the bug and the malformed message
    assert status["raw_messages"] == 4 == status["received_batches"] + status["dropped_total"]
    lines = [r for r in caplog.records if "handler failed" in r.getMessage()]
    assert len(lines) == 1 and r"RuntimeError: a bug" in lines[0].getMessage() and lines[0].exc_info is None


def test_the_guard_logs_the_first_failure_of_a_cause_and_then_only_counts(caplog):
    guard = Guard("svc", logging.getLogger("t.guard"))
    with caplog.at_level(logging.ERROR, "t.guard"):
        for _ in range(5):
            assert guard.run("raw", lambda: 1 / 0) is None
        assert guard.run("raw", lambda: 7) == 7
    assert guard.drops.counts == {"raw:handler-ZeroDivisionError": 5}
    assert len(caplog.records) == 1
    assert refusal(ValueError("limit must be a whole number"), "svc") == "limit must be a whole number"
    with pytest.raises(KeyboardInterrupt):  # how a process is asked to end: not swallowed
        guard.run("raw", _interrupt)


def _interrupt() -> None:
    raise KeyboardInterrupt


def test_store_errors_say_full_disk_unreadable_disk_or_damage_apart(tmp_path):
    from services.calibrator.store import store_error

    def err(code: int, text: str) -> StoreError:
        exc = sqlite3.OperationalError(text)
        exc.sqlite_errorcode = code
        return store_error(tmp_path / "c.db", "write", exc)

    assert "disk full" in str(err(13, "database or disk is full"))
    assert "could not write its database" in str(err(10, "disk I/O error"))
    assert "restore it from a backup" in str(err(11, "database disk image is malformed"))


# ------------------------------------------------------------------------------------------------- compass
def _compass_loop(monkeypatch):
    from services.compass import service as compass_service

    class Session:
        def __init__(self) -> None:
            self.puts: list[str] = []

        def get(self, *args: Any, **kwargs: Any) -> FakeChannel:
            return FakeChannel()

        def put(self, key: str, payload: bytes) -> None:
            self.puts.append(key)

    settings = compass_service.CompassSettings(max_devices=100)
    compass = compass_core(Earth(5.0), 1)
    session = Session()
    return compass_service._Loop(session, compass, settings), compass, session


class FakeSample:
    def __init__(self, key: str, payload: bytes) -> None:
        self.key_expr, self._payload = key, payload

    @property
    def payload(self) -> Any:
        return type("P", (), {"to_bytes": lambda _self: self._payload, "__len__": lambda _self: len(self._payload)})()


def test_compass_survives_a_failing_calibration_handler_and_a_failing_drain(monkeypatch):
    from services.common import status_board
    from services.compass import service as compass_service
    from services.compass.intake import PayloadIntake

    loop, compass, session = _compass_loop(monkeypatch)
    cal, alert_q, raw = FakeChannel(), FakeChannel(), PayloadIntake()
    monkeypatch.setattr(compass, "accept_calibration", lambda *a: (_ for _ in ()).throw(RuntimeError("bug")))
    cal.items.append(FakeSample(f"{PREFIX}/d1/calibration", b"x"))
    monkeypatch.setattr(compass, "encode", lambda *a: (_ for _ in ()).throw(MemoryError("too big")))
    raw.offer_many([FakeSample(f"{PREFIX}/d1/raw", _raw("d1", i)) for i in range(3)])
    ends = compass_service._Ends(raw, cal, alert_q)  # type: ignore[arg-type]
    loop.step(ends, "c")
    monkeypatch.undo()
    monkeypatch.setattr(status_board, "REFRESH_S", 0.0)  # the loop writes its status after every step
    raw.offer_many([FakeSample(f"{PREFIX}/d1/raw", _raw("d1", 9))])
    loop.step(ends, "c")
    query = FakeQuery(f"{PREFIX}/@status/c")
    loop.board.answer(query)  # as Zenoh's thread does
    status = query.replies[0][1]
    assert status["dropped"] == {"calibration:handler-RuntimeError": 1, "raw:handler-MemoryError": 3}
    assert session.puts == [f"{PREFIX}/d1/heading"]  # the next drain got its heading


# ------------------------------------------------------------------------------------------------- edge
def test_edge_status_query_that_fails_gets_an_error_and_the_next_is_answered(monkeypatch):
    from services.edge.service import EdgeStatus
    from services.edge.settings import EdgeSettings

    status = EdgeStatus(EdgeSettings(device="e1", emulate=True))
    as_dict = status.as_dict
    monkeypatch.setattr(status, "as_dict", lambda: {"bad": object()})  # not packable: a bug
    first = FakeQuery("magnet/@status/edge-e1")
    status.answer_status(first)
    monkeypatch.setattr(status, "as_dict", as_dict)
    second = FakeQuery("magnet/@status/edge-e1")
    status.answer_status(second)
    assert first.errors and first.dropped and not first.replies
    assert second.replies[0][1]["dropped"] == {"query:status:handler-TypeError": 1}


# ------------------------------------------------------------------------------------------------- dashboard
class FailingControl:
    def __init__(self) -> None:
        self.fail = True

    def calibrate(
        self, device: str, action: str, method: str | None, to: str | None = None, by: str | None = None
    ) -> tuple[list[dict], list[str]]:
        if self.fail:
            self.fail = False
            raise OSError("zenoh session closed")
        return [{"ok": True, "message": "started"}], []

    def history(self, device: str, limit: int) -> tuple[list[dict], list[str]]:
        raise RuntimeError("bug")


def test_dashboard_http_handler_failure_is_a_500_with_json_and_the_next_request_is_served():
    state = FleetState(None)
    state.on_alive("d1", True)
    client = TestClient(create_app(state, FailingControl(), "tok"), base_url="http://127.0.0.1")
    headers = {"Authorization": "Bearer tok"}
    first = client.post("/api/devices/d1/calibrate", json={"action": "start"}, headers=headers)
    assert first.status_code == 500 and first.json() == {"error": "zenoh session closed"}
    second = client.post("/api/devices/d1/calibrate", json={"action": "start"}, headers=headers)
    assert second.status_code == 200 and second.json()["ok"]
    third = client.get("/api/devices/d1/history")
    assert third.status_code == 500 and "RuntimeError" in third.json()["error"]
    assert client.get("/api/fleet").status_code == 200
    assert state.dropped.counts == {"http:calibrate:handler-OSError": 1, "http:history:handler-RuntimeError": 1}


def test_dashboard_ingest_drops_and_counts_a_message_whose_handler_fails(monkeypatch):
    from services.dashboard.ingest import Ingest

    state = FleetState(None)
    ingest = Ingest.__new__(Ingest)
    ingest.prefix, ingest.state, ingest.guard = PREFIX, state, Guard("dashboard", logging.getLogger("t"), state.dropped)
    monkeypatch.setattr(state, "on_calibration", lambda m: (_ for _ in ()).throw(RuntimeError("bug")))
    record = wire.pack(_record("d1", 1).to_record())
    ingest.guard.run("calibration", ingest._on_calibration, f"{PREFIX}/d1/calibration", record)
    monkeypatch.undo()
    ingest.guard.run("calibration", ingest._on_calibration, f"{PREFIX}/d1/calibration", record)
    assert state.dropped.counts == {"calibration:handler-RuntimeError": 1}
    assert "d1" in state.rows
