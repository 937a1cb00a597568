"""Issue 32: a flood of new ids made one drain of the compass take seconds (each new device's state made), and the
status and the stop signal are only seen between drains. A slow drain now makes the next ones small enough for
``STEP_BUDGET_S``; fast ones let them grow back. The loop's clock is replaced (no timing here)."""

from __future__ import annotations

from services.compass import service as compass_service
from services.compass.service import MAX_DRAIN, STEP_BUDGET_S, CompassSettings, _Loop, build_core


class Session:
    def get(self, *args: object, **kwargs: object) -> list[object]:
        return []


def test_a_slow_drain_shrinks_the_next_and_fast_ones_let_it_grow_back(monkeypatch) -> None:
    settings = CompassSettings()
    loop = _Loop(Session(), build_core(settings), settings)  # type: ignore[arg-type]
    assert loop.time_limit == MAX_DRAIN
    loop._pace(8000, 8 * STEP_BUDGET_S)  # 8,000 new ids took 2 s
    assert loop.time_limit == 1000
    loop._pace(1000, STEP_BUDGET_S * 0.9)  # within the budget: kept
    assert loop.time_limit == 1000
    for _ in range(4):
        loop._pace(loop.time_limit, STEP_BUDGET_S / 10)
    assert loop.time_limit == MAX_DRAIN
    loop._pace(8000, 1000.0)
    assert loop.time_limit == 100  # never below 100 messages a drain


def test_the_loop_takes_no_more_than_the_time_limit(monkeypatch) -> None:
    settings = CompassSettings()
    loop = _Loop(Session(), build_core(settings), settings)  # type: ignore[arg-type]
    asked: list[int] = []

    class Raw:
        def hand_over_drops(self, *args: object) -> None:
            pass

        def __len__(self) -> int:  # messages still waiting after a take
            return 0

        def take(self, limit: int, max_bytes: int) -> list[tuple[str, bytes]]:
            asked.append(limit)
            return [("magnet/x/raw", b"")] * min(limit, 5000)

    clock = iter([0.0, 2.0, 10.0, 10.01])
    monkeypatch.setattr(compass_service.time, "perf_counter", lambda: next(clock))
    monkeypatch.setattr(loop, "headings_of", lambda samples: None)
    ends = compass_service._Ends(Raw(), [], [])  # type: ignore[arg-type]
    monkeypatch.setattr(compass_service, "drain", lambda handler, limit: [])
    loop.step(ends, "c")  # 5,000 in 2 s
    loop.step(ends, "c")
    assert asked == [MAX_DRAIN, int(5000 * STEP_BUDGET_S / 2.0)]
