"""A calibrator whose token appears after the compass's start-up query (it came up later, or came back) is asked for
every calibration: its own start-up publication may have gone out before Zenoh linked the two. That was why
test_compass_without_calibrators timed out in loaded CI runs, the compass holding 0 records: its session opened a
few ms before the calibrator listened. Tokens that appear together make one query, at most one a second; a token
that goes away makes none (the loop's clock replaced, its session a stand-in that counts queries). Then the same
with processes: a compass up first gets the record of a calibrator started after it, with no raw batch sent."""

from __future__ import annotations

import time
from types import SimpleNamespace

import numpy as np
import pytest
import zenoh
from helpers import NO_SCOUT, connect_args, free_ports, listen_args, magnet_json, wait_for

from magnet import wire
from magnet.model import Calibration
from services.calibrator.store import CalibrationStore
from services.compass import service as compass_service
from services.compass.service import REQUERY_JOINED_S, CompassSettings, _Ends, _Loop, build_core


class Session:
    def __init__(self) -> None:
        self.asked: list[str] = []

    def get(self, key: str, **kwargs: object) -> list[object]:
        self.asked.append(key)
        return []


class Raw:
    def hand_over_drops(self, *args: object) -> None:
        pass

    def __len__(self) -> int:  # messages still waiting after a take
        return 0

    def take(self, limit: int, max_bytes: int) -> list[tuple[str, bytes]]:
        return []


def _token(name: str, alive: bool) -> SimpleNamespace:
    kind = zenoh.SampleKind.PUT if alive else zenoh.SampleKind.DELETE
    return SimpleNamespace(key_expr=f"magnet/@alive/calibrator/{name}", kind=kind)


def test_a_calibrator_token_that_appears_makes_the_compass_ask_for_every_calibration_again(monkeypatch) -> None:
    now = [100.0]
    monkeypatch.setattr(compass_service.time, "monotonic", lambda: now[0])
    session, settings = Session(), CompassSettings()
    loop = _Loop(session, build_core(settings), settings)  # type: ignore[arg-type]
    assert session.asked == ["magnet/*/calibration"], "the start-up query"
    tokens: list[SimpleNamespace] = []
    ends = _Ends(Raw(), "calibrations", "alerts", "vehicles", "calibrators")  # type: ignore[arg-type]

    def drain(handler: object, limit: int) -> list[object]:
        taken = list(tokens) if handler == "calibrators" else []
        if handler == "calibrators":
            tokens.clear()
        return taken

    monkeypatch.setattr(compass_service, "drain", drain)

    def step(seconds: float, *new_tokens: SimpleNamespace) -> int:
        now[0] += seconds
        tokens.extend(new_tokens)
        before = len(session.asked)
        loop.step(ends, "c")
        return len(session.asked) - before

    assert step(0.1) == 0, "no token: nothing more asked"
    assert step(0.1, _token("a", True), _token("b", True)) == 0, "within a second of the start-up query: it waits"
    assert step(REQUERY_JOINED_S / 2) == 0
    assert step(REQUERY_JOINED_S / 2) == 1, "then the two tokens make one query"
    assert session.asked[-1] == "magnet/*/calibration"
    assert step(5.0) == 0, "asked once, not again"
    assert step(0.1, _token("a", False)) == 0 and step(5.0) == 0, "a token gone makes no query"
    assert step(0.1, _token("a", True)) == 1, "a calibrator back, long after the last query: asked at once"
    assert loop.core.status("c").calibrators_state == "present"


def _status(port: int) -> dict[str, object] | None:
    code, lines = magnet_json("get", "status", "compass", *NO_SCOUT, *connect_args(port), "--timeout", "2", timeout=60)
    return lines[0] if code == 0 and lines else None


@pytest.mark.integration
def test_a_compass_up_before_its_calibrator_gets_the_records_in_force(procs, tmp_path) -> None:
    record = wire.DeviceCalibration(
        "late", time.time_ns(), Calibration("ellipsoid", np.array([12.0, -7.0, 4.0]), np.eye(3))
    )
    with CalibrationStore(tmp_path / "c.db") as store:
        store.save(record)
    cal_port, comp_port = free_ports(2)
    procs.start("compass", "compass", *listen_args(comp_port), *connect_args(cal_port))
    first = wait_for(lambda: _status(comp_port), 60, "the compass to answer (its start-up query asked nobody)")
    assert (first["calibrations"], first["calibrators_state"]) == (0, "unseen")
    procs.start("calibrator", "calibrator", "--db", str(tmp_path / "c.db"), *listen_args(cal_port))
    held = wait_for(
        lambda: (s := _status(comp_port)) and s["calibrations"] == 1 and s,
        60,  # before the compass asked again on the calibrator's token, it held 0 records for good (37 s seen)
        "the compass to hold the record of the calibrator started after it",
    )
    assert held["calibrators_state"] == "present" and held["received_batches"] == 0, "no raw batch asked for it"
