"""Issue 32: the compass's status waited for the drain in progress (a flood of new ids: 258 of 259 within 1 s in a
10-minute soak). It is now answered from Zenoh's thread with what the loop last wrote: a query asked while the loop
is inside a drain that does not end is answered at once, with the age of what it says."""

from __future__ import annotations

import threading

from helpers import StatusQuery as Query

from magnet import wire
from services.common.status_board import REFRESH_S
from services.compass import service as compass_service
from services.compass.service import CompassSettings, _Loop, build_core


class Session:
    def get(self, *args: object, **kwargs: object) -> list[object]:
        return []


def test_status_is_answered_while_the_loop_is_stuck_in_a_drain(monkeypatch) -> None:
    settings = CompassSettings()
    loop = _Loop(Session(), build_core(settings), settings)  # type: ignore[arg-type]
    inside, release = threading.Event(), threading.Event()

    def stuck(samples: object) -> None:
        inside.set()
        release.wait(30)  # a drain that takes as long as the test likes

    class Raw:
        def hand_over_drops(self, *args: object) -> None:
            pass

        def __len__(self) -> int:  # messages still waiting after a take
            return 0

        def take(self, limit: int, max_bytes: int) -> list[tuple[str, bytes]]:
            return [("magnet/x/raw", b"")]

    monkeypatch.setattr(loop, "headings_of", stuck)
    monkeypatch.setattr(compass_service, "drain", lambda handler, limit: [])
    ends = compass_service._Ends(Raw(), [], [])  # type: ignore[arg-type]
    worker = threading.Thread(target=loop.step, args=(ends, settings.name))
    worker.start()
    try:
        assert inside.wait(10)
        query = Query()
        loop.board.answer(query)  # as Zenoh's thread does, while the loop is in its drain
        assert query.dropped and query.errors == []
        [(key, status)] = query.replies
        assert key == wire.status_key(wire.DEFAULT_PREFIX, settings.name) and status["service"] == "compass"
        assert status["status_age_s"] >= 0.0
    finally:
        release.set()
        worker.join(10)


def test_the_loop_writes_its_status_at_most_every_refresh_s() -> None:
    settings = CompassSettings()
    loop = _Loop(Session(), build_core(settings), settings)  # type: ignore[arg-type]
    now = [0.0]
    loop.board.clock = lambda: now[0]
    loop.board.write({"received_batches": 1})
    assert not loop.board.due()
    now[0] += REFRESH_S
    assert loop.board.due()
    query = Query()
    now[0] += 2.0
    loop.board.answer(query)
    assert query.replies[0][1] | {"v": 1} == {"v": 1, "received_batches": 1, "status_age_s": 2.05}
    loop.board.latest = None  # nothing written yet: an error the asker can act on, not a silence
    starting = Query()
    loop.board.answer(starting)
    assert starting.replies == [] and b"starting" in starting.errors[0] and starting.dropped
