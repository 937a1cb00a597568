"""Samples missing within a run (``magnet.calibration.sample_runs``): the sample after k missing ones is taken over
its k + 1 periods, a stall cuts the run, a stream without gaps is as before."""

from __future__ import annotations

import numpy as np

from magnet.calibration.sample_runs import MOST_MISSING, RecentRuns, whole_periods

PERIOD_NS = 20_000_000
RATE_RADS = np.array([0.0, 0.0, 1.0])  # 1 rad/s about z


def _ring(t_ns: np.ndarray, batch: int = 25) -> RecentRuns:
    ring = RecentRuns(capacity=10_000)
    for seq, start in enumerate(range(0, len(t_ns), batch)):
        t = t_ns[start : start + batch]
        ring.add(np.ones((len(t), 3)), np.ones((len(t), 3)), np.tile(RATE_RADS, (len(t), 1)), t, seq)
    return ring


def test_dropped_samples_keep_the_run_whole_and_its_rotation_the_devices():
    rng = np.random.default_rng(1)
    keep = rng.random(3000) >= 0.02
    keep[0] = True
    t_ns = PERIOD_NS * np.flatnonzero(keep).astype(np.int64)
    run = _ring(t_ns).longest()
    assert run is not None and len(run) == keep.sum()  # one run: no drop of more than MOST_MISSING in a row here
    assert run.periods is not None and run.period_s == PERIOD_NS / 1e9
    turned_rad = (run.turn_rads * run.period_s).sum(axis=0)[2] - RATE_RADS[2] * run.period_s  # the first: no step
    np.testing.assert_allclose(turned_rad, RATE_RADS[2] * (t_ns[-1] - t_ns[0]) / 1e9)
    spanned_s = (t_ns[-1] - t_ns[0]) / 1e9 + run.period_s
    np.testing.assert_allclose(run.turned_deg()[2], np.degrees(RATE_RADS[2] * spanned_s))
    tail = run.tail(10.0)
    assert tail.periods is not None and len(tail.periods) == len(tail)


def test_a_stall_cuts_the_run_and_its_rotation_is_not_made_up():
    t_ns = PERIOD_NS * np.concatenate([np.arange(1000), np.arange(1000 + MOST_MISSING + 1, 1400)]).astype(np.int64)
    run = _ring(t_ns).longest()
    assert run is not None and len(run) == 1000 and run.periods is None
    bridged = PERIOD_NS * np.concatenate([np.arange(1000), np.arange(1000 + MOST_MISSING, 1400)]).astype(np.int64)
    run = _ring(bridged).longest()
    assert run is not None and len(run) == len(bridged)
    assert run.periods is not None and run.periods.max() == MOST_MISSING + 1 and (run.periods > 1).sum() == 1


def test_a_stream_without_gaps_is_integrated_as_before_to_the_bit():
    t_ns = PERIOD_NS * np.arange(2000, dtype=np.int64)
    run = _ring(t_ns).longest()
    assert run is not None and run.periods is None and run.turn_rads is run.gyr_rads
    jitter = t_ns + np.random.default_rng(2).integers(-5_000_000, 5_000_000, len(t_ns))  # 5 ms at 20 ms: no gap
    assert whole_periods(np.sort(jitter), PERIOD_NS) is None


def test_stamps_in_pairs_are_not_read_as_gaps():
    pairs = (10_000_000 * (np.arange(200) // 2) + 750_000 * (np.arange(200) % 2)).astype(np.int64)  # PX4-like
    assert whole_periods(pairs, float(np.median(np.diff(pairs)))) is None
    assert whole_periods(np.array([0], dtype=np.int64), 1.0) is None
