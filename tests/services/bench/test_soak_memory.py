"""The soak's judgement of "memory flat after warm-up" (``services.bench.soak_memory``): steady states compared, not
single samples, and a leak still fails it.

``soak_rss_samples.json``: every RSS sample of the compass and the dashboard in a real 10-minute soak
(``magnet bench soak --minutes 10 --samples``, main at b2b2117, 2026-12-04 20:31-20:41 UTC, load average 4-10), and
``dashboard-2`` the dashboard's in another (with its gate at accept, 20:54-21:04 UTC, load average 7-10):
[t_s, round, MB] each. The compass was killed at the start of rounds 2, 5 and 8; the dashboard ran throughout."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from services.bench.soak_memory import FLAT_RULE, MemoryWatch, bound_mb, memory_lines

SAMPLES = json.loads((Path(__file__).parent / "soak_rss_samples.json").read_text())
KILLED_AT_ROUNDS = (2, 5, 8)  # the compass's kills: each starts a new process


def watch(series: list[list[float]], leak=lambda t, r: 0.0, name: str = "s") -> MemoryWatch:
    """A ``MemoryWatch`` fed ``series`` ([t_s, round, MB]) plus ``leak(t_s, round)`` MB."""
    out = MemoryWatch()
    for t, r, mb in series:
        out.sample(name, mb + leak(t, int(r)), int(r), t_s=t)
    return out


def per_life(series: list[list[float]], mb_per_min: float):
    """A leak of ``mb_per_min`` that starts again with each of the compass's lives (a leak of its process)."""
    born = {r: min(t for t, rr, _ in series if rr == r) for r in KILLED_AT_ROUNDS}

    def leak(t: float, r: int) -> float:
        start = max([0.0] + [born[k] for k in KILLED_AT_ROUNDS if k <= r])
        return mb_per_min * (t - start) / 60.0

    return leak


@pytest.mark.parametrize("service", ["compass", "dashboard", "dashboard-2"])
def test_a_real_soaks_services_are_flat(service):
    m = watch(SAMPLES[service]).services["s"]
    assert m.flat() is True
    assert m.warmup_levels is not None and m.later_levels is not None and m.end_mb is not None


@pytest.mark.parametrize("service", ["compass", "dashboard"])
def test_a_bursts_peak_in_a_later_round_is_not_a_level(service):
    """What made the rule before say `NO` in one run of five: one 0.5 s sample of a later round's burst above every
    sample of round 1. Two samples 30 MB higher in round 6 move no level; the highest sample still shows them."""
    series = [list(s) for s in SAMPLES[service]]
    in_round_6 = [i for i, (_, r, _) in enumerate(series) if r == 6]
    for i in in_round_6[40:42]:
        series[i][2] += 30.0
    m = watch(series).services["s"]
    assert m.flat() is True
    assert m.later_high_mb is not None and m.warmup_mb is not None
    assert m.later_high_mb > bound_mb(m.warmup_mb)  # the old rule's comparison: not flat


def test_a_leak_over_the_whole_run_fails_it():
    """The dashboard runs the whole soak: a leak of 1.5 MB a minute (15 MB in 10 minutes) is not flat, nor one that
    only starts after warm-up; no leak is."""
    series = SAMPLES["dashboard"]
    assert watch(series, lambda t, r: 1.5 * t / 60.0).services["s"].flat() is False
    assert watch(series, lambda t, r: 1.5 * max(0.0, t - 100.0) / 60.0).services["s"].flat() is False
    assert watch(series, lambda t, r: 0.0).services["s"].flat() is True


def test_a_leak_in_each_of_the_compasss_lives_fails_it():
    """The compass is restarted every third round, so a leak of its process starts again each life (3 minutes): one
    of 5 MB a minute reaches the bound within a life; a leak that survives restarts (a file, a shared segment) is
    the whole run's, as above."""
    series = SAMPLES["compass"]
    assert watch(series, per_life(series, 5.0)).services["s"].flat() is False
    assert watch(series, lambda t, r: 1.5 * t / 60.0).services["s"].flat() is False


def synthetic(rounds: int = 10, per_round: int = 110, level: float = 80.0, burst=lambda r: 0.0, seed: int = 1):
    """Round 0 quiet at 60 MB, then rounds of ``per_round`` samples at ``level`` (noise 1 MB) with 10 % of each
    round's samples ``burst(round)`` MB higher (a burst of a few seconds), and a quiet end at ``level``."""
    rng, out, t = np.random.default_rng(seed), [], 0.0
    for r in range(rounds + 1):
        for i in range(per_round if r else 50):
            extra = burst(r) if r and i % 10 == 0 else 0.0
            out.append([t, r, (level if r else 60.0) + extra + rng.normal(0.0, 1.0)])
            t += 0.55
    return out


def test_bursts_are_printed_and_what_they_leave_behind_is_judged():
    """The second soak's dashboard: its 90 % quantile 77 MB in round 1 (whose first 40 samples came before the first
    flood filled its table) and up to 88 after, with bursts of the same height in every round: flat, its levels
    77-81. A burst that leaves 1.5 MB behind every round is a leak and fails."""
    m = watch(SAMPLES["dashboard-2"]).services["s"]
    assert m.flat() is True and m.warmup_levels is not None and m.later_levels is not None
    assert m.later_levels[1] > bound_mb(m.warmup_levels[1])  # the upper quantile: printed, not judged
    assert watch(synthetic(burst=lambda r: 12.0)).services["s"].flat() is True
    leaves = watch(synthetic(), lambda t, r: 1.5 * max(0, r - 1)).services["s"]
    assert leaves.flat() is False


def test_what_is_not_judged():
    quiet = MemoryWatch()
    for i in range(50):
        quiet.sample("s", 60.0, round_no=0, t_s=0.5 * i)
    assert quiet.services["s"].flat() is None  # no round 1 yet
    series = synthetic()
    round_4 = [s for s in series if s[1] == 4]
    short = [s for s in series if s[1] != 4 or s in round_4[:5]]  # round 4: the service down most of it
    short += [[t, 4, 200.0] for t, _, _ in round_4[5:8]]  # and high for the few samples it had
    short.sort()
    m = watch(short).services["s"]
    assert m.levels(4) is None and m.flat() is True
    small = watch(synthetic(level=30.0), lambda t, r: 6.0 * (r > 5)).services["s"]
    assert small.flat() is True  # 6 MB over 30: 20 %, within the floor of 10 MB for a small process


def test_the_report_says_the_rule_and_each_figure():
    lines = memory_lines(watch(SAMPLES["compass"], name="compass"))
    text = "\n".join(lines)
    assert FLAT_RULE in text and "compass" in text and "yes" in text
    leaky = "\n".join(memory_lines(watch(SAMPLES["dashboard"], lambda t, r: 2.0 * t / 60.0, name="dashboard")))
    assert "NO" in leaky and "highest sample" in leaky
