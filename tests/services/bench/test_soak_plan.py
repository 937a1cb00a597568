"""``magnet bench soak`` without processes: its schedule of faults and how its figures are counted."""

from __future__ import annotations

import pytest

from services.bench.soak_plan import (
    CYCLE,
    ROUND_LEN,
    SETTLE_S,
    WARMUP_S,
    DropTotals,
    HeadingGaps,
    MemoryWatch,
    calibrations_lost,
    report,
    round_of,
    schedule,
)


def test_a_three_minute_soak_meets_every_kind_of_fault_and_ends_quiet():
    faults = schedule(3)
    assert {f.label for f in faults} == {f.label for f in CYCLE}  # kills of each service, router, bombs, flood, disk
    assert {f.target for f in faults if f.kind == "kill"} == {"calibrator", "compass", "edge"}
    times = [f.at_s for f in faults]
    assert times == sorted(times) and times[0] == WARMUP_S
    assert all(f.at_s + f.hold_s <= 180 - SETTLE_S for f in faults)


def test_a_longer_soak_goes_round_the_cycle_again_and_a_bad_length_is_refused():
    faults = schedule(10)
    assert len(faults) > 3 * len(CYCLE)
    assert [f.label for f in faults[: len(CYCLE)]] == [f.label for f in faults[len(CYCLE) : 2 * len(CYCLE)]]
    assert schedule(0.5) == []  # shorter than warm-up and settling: no fault
    for bad in (0, -1, float("nan"), float("inf")):
        with pytest.raises(ValueError, match="--minutes"):
            schedule(bad)


def test_gaps_are_between_consecutive_headings_of_one_device():
    gaps = HeadingGaps()
    for t in (0.0, 0.1, 0.2):
        gaps.on_heading("a", t)
        gaps.on_heading("b", t)
    gaps.on_heading("a", 2.2, "kill compass")  # a 2 s gap after a kill
    gaps.on_heading("c", 50.0, "flood")  # a new device: its first heading is no gap
    assert gaps.longest_s == pytest.approx(2.0) and (gaps.device, gaps.after) == ("a", "kill compass")
    gaps.on_heading("b", 1.2, "kill compass")
    gaps.on_heading("b", 1.5, "router")
    assert gaps.by_fault == {"kill compass": pytest.approx(2.0), "router": pytest.approx(0.3)}


def test_drops_add_up_over_the_runs_of_a_service_and_calibrations_lost_are_the_ones_not_served():
    drops = DropTotals()
    drops.update("compass", 1, {"raw:not-a-map": 3})
    drops.update("compass", 1, {"raw:not-a-map": 5})  # the same run answered again: its latest counts
    drops.update("compass", 2, {"raw:not-a-map": 2, "raw:too-large": 1})  # restarted: counts from zero
    assert drops.totals() == {"compass": {"raw:not-a-map": 7, "raw:too-large": 1}}
    published = {"a": 10, "b": 20, "c": 30}
    assert calibrations_lost(published, {"a": 10, "b": 25}) == ["c"]  # b has a newer one: not lost
    assert calibrations_lost(published, {"a": 9, "b": 20, "c": 30}) == ["a"]  # an older one served: lost


def test_memory_and_the_report():
    memory = MemoryWatch()
    memory.sample("compass", 100.0, round_no=0)
    memory.sample("compass", 150.0, round_no=1)
    memory.sample("compass", 400.0, round_no=1)
    memory.sample("compass", None, round_no=2)  # not running at that moment
    memory.sample("compass", 160.0, round_no=2)
    m = memory.services["compass"]
    assert (m.high_mb, m.last_mb, m.by_round) == (400.0, 160.0, {0: 100.0, 1: 400.0, 2: 160.0})
    assert m.growth_mb == -240.0  # the highest samples: the later rounds' below the first's
    assert m.flat() is None  # too few samples in round 1 to judge (tests/services/bench/test_soak_memory.py)
    gaps = HeadingGaps()
    text = report(2, ["kill compass"], {"a": 1}, {}, gaps, memory, DropTotals())
    assert "calibrations lost: 1 of 1 published: a" in text and "compass" in text and "400" in text
    assert m.warmup_mb == 400.0 and m.later_high_mb == 160.0


def test_a_leak_shows_as_growth_after_the_first_round_and_a_bound_does_not():
    leak, bounded = MemoryWatch(), MemoryWatch()
    for r in range(5):
        leak.sample("calibrator", 70.0 + 10 * r, round_no=r)
        bounded.sample("calibrator", 70.0 if r == 0 else 120.0, round_no=r)
    assert leak.services["calibrator"].growth_mb == 30.0
    assert bounded.services["calibrator"].growth_mb == 0.0
    once = MemoryWatch()
    once.sample("calibrator", 70.0, round_no=1)
    assert once.services["calibrator"].growth_mb is None  # no second round yet: nothing to say


def test_rounds_follow_the_cycle():
    assert [round_of(n) for n in (0, 1, ROUND_LEN, ROUND_LEN + 1, 2 * ROUND_LEN + 1)] == [0, 1, 1, 2, 3]
    rounds = [CYCLE[i : i + ROUND_LEN] for i in range(0, len(CYCLE), ROUND_LEN)]
    assert [r[0].label for r in rounds] == ["kill calibrator", "kill compass", "kill edge"]  # one kill a round
    assert all(f.kind != "kill" for r in rounds for f in r[1:])  # so each service lives through three rounds


def test_memory_is_kept_per_fault_to_show_what_grows_when():
    from services.bench.soak_plan import MemoryWatch

    watch = MemoryWatch()
    for rss, fault in [(60, "warm-up"), (65, "bombs"), (90, "bombs"), (70, "flood"), (300, "flood"), (80, "router")]:
        watch.sample("compass", rss, round_no=1, fault=fault)
    assert watch.services["compass"].by_fault == {"warm-up": 60, "bombs": 90, "flood": 300, "router": 80}
    assert watch.services["compass"].high_mb == 300 and watch.services["compass"].last_mb == 80


def test_the_soak_meets_the_front_doors_faults_and_prints_their_figures():
    """Issue 32: the soak adds a deleted database, MAVLink and ROS 2 floods and 2,000 dashboard streams, and prints
    whether status was always answered within 1 s."""
    from services.bench.soak_plan import STATUS_LIMIT_S, StatusTimes, front_lines

    kinds = {f.kind for f in schedule(3)}
    assert {"delete-db", "flood", "bombs"} <= kinds
    times = StatusTimes()
    for seconds, grace in ((0.2, False), (STATUS_LIMIT_S + 0.5, False), (None, False), (None, True)):
        times.add("compass", seconds, grace, "flood")
    [head, line] = times.lines()
    assert "within 1 s" in head
    assert line == "  compass: 1 of 3, slowest 1.50 s, unanswered 1 (not counted 1); late or missed after flood 2"
    lines = front_lines(
        {"mavedge": {"devices": 65}, "compass": {"sinks": {"ros2_topics": 256, "ros2_topics_evicted": 3}}},
        {"mavlink": [{"sent": 20_000}], "streams": [{"answered": {"200": 64, "503": 1936}}]},
        {"times": 2, "with_file": 7, "while_gone": 0, "gone_seen": 2, "seen_after_s": 1.5},
        ("mav1-mag1", 0.4, 900),
    )
    text = "\n".join(lines)
    assert (
        "65 devices" in text and "longest heading gap 0.40 s" in text and "256 devices with topics, 3 evicted" in text
    )
    assert "{'200': 64, '503': 1936}" in text and "published while gone (lost with the file) 0" in text
    assert "dashboard streams: every request answered: 64 streamed, 1936 refused by design" in text


def test_a_503_is_a_designed_refusal_and_a_stream_closed_without_an_answer_is_lost():
    from services.bench.soak_plan import stream_verdict

    line = stream_verdict({"200": 64, "503:streams": 10, "503:connections": 1926}, 0)
    assert "every request answered" in line and "1936 refused by design" in line
    assert "the app's limit of streams 10, the limit of connections 1926" in line and "0 lost" in line
    line = stream_verdict({"200": 64, "503:connections": 100, "none": 1826, "silent": 5}, 10)
    assert "NOT every request answered" in line and "1841 lost (closed without an answer 1826" in line
    assert "no answer within the hold and the grace 5, not accepted 10)" in line


def test_a_stream_answered_after_the_hold_is_slow_not_lost():
    from services.bench.soak_plan import front_lines, stream_verdict

    line = stream_verdict({"200": 64, "503:connections": 1936}, 0, late=300, grace_s=10)
    assert "every request answered" in line and "300 of these answered only after the hold (within 10 s" in line
    results = {"streams": [{"answered": {"200": 3, "503:connections": 7}, "refused": 0, "late": 2, "grace_s": 10.0}]}
    deleted = {"times": 0, "with_file": 0, "while_gone": 0, "gone_seen": 0, "seen_after_s": 0.0}
    lines = front_lines({}, results, deleted, ("v", 0.0, 0))
    assert any("every request answered" in x and "2 of these answered only after the hold" in x for x in lines)


def test_every_round_floods_before_its_bombs_so_the_warmup_round_meets_full_tables():
    """Round 1 is the warm-up's pass of every fault (``FLAT_RULE``): its bombs and 2,000 dashboard streams must meet
    the tables a flood fills, as every later round's do, or later rounds are judged against a lighter load."""
    kinds = [fault.kind for fault in CYCLE]
    for start in range(0, len(CYCLE), ROUND_LEN):
        one_round = kinds[start : start + ROUND_LEN]
        assert one_round.index("flood") < one_round.index("bombs"), one_round
