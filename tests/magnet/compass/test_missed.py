"""Samples missing within a batch (``magnet.compass.missed``): the sample after them turns the filter over their time
and the batch's period counts them, so a phone that drops 2 % of its samples keeps its heading."""

from __future__ import annotations

import numpy as np
from compass_steps import WALL_NS, heading_errors_deg
from fusion_helpers import rotating_device

from magnet import wire
from magnet.attitude.heading_gate import _LAYOUT, HeadingGate
from magnet.attitude.turn_gate import TurnGate
from magnet.compass.filters import DeviceFilters
from magnet.compass.missed import MOST_MISSING, spanned
from magnet.simulator import SensorErrors, SimulatorConfig, Trajectory, simulate


def test_whole_missing_steps_are_counted_and_jitter_is_not():
    t_ns = np.array([0, 20, 40, 80, 100, 1000, 1021, 1039, 1061, 1080]) * 10**6
    gyr = np.ones((10, 3))
    edges = np.array([0, 5, 10])
    scaled, spans, stalled = spanned(gyr, t_ns, edges)
    np.testing.assert_array_equal(scaled[:, 0], [1, 1, 1, 2, 1, 1, 1, 1, 1, 1])
    np.testing.assert_array_equal(spans, [5, 4])
    assert not stalled.any()
    uniform, spans, _ = spanned(gyr, np.arange(10) * 20 * 10**6, edges)
    assert uniform is gyr and list(spans) == [4, 4]


def test_a_walk_that_drops_two_percent_of_its_samples_keeps_its_heading():
    errors = SensorErrors.phone(np.random.default_rng([1, 26]), 50.0)
    run = simulate(SimulatorConfig(trajectory=Trajectory.WALK_HAND, count=3000, errors=errors, seed=1))
    keep = np.random.default_rng(7).random(len(run.t_s)) >= 0.02
    keep[0] = True
    record = [(10.0, wire.encode_calibration("phone", errors.true_calibration(50.0), WALL_NS))]
    whole = heading_errors_deg(run, record)

    class Dropped:  # the run's samples that came
        t_s, mag_ut, acc_ms2, gyr_rads, quat_wxyz = (
            getattr(run, name)[keep] for name in ("t_s", "mag_ut", "acc_ms2", "gyr_rads", "quat_wxyz")
        )

    dropped = heading_errors_deg(Dropped, record)
    scored = run.t_s > 20.0
    rms_whole = float(np.sqrt(np.nanmean(whole[scored] ** 2)))
    rms_dropped = float(np.sqrt(np.nanmean(dropped[scored[keep]] ** 2)))
    assert rms_dropped < 1.5 * rms_whole + 0.5, (rms_dropped, rms_whole)


def test_a_stall_counts_whole_in_the_period_but_is_made_up_for_only_up_to_the_limit():
    t_ns = np.array([0, 20, 40, 240, 260, 280]) * 10**6  # 9 samples missing after the third
    gyr = np.ones((6, 3))
    scaled, spans, stalled = spanned(gyr, t_ns, np.array([0, 6]))
    np.testing.assert_array_equal(scaled[:, 0], [1, 1, 1, MOST_MISSING + 1, 1, 1])
    assert list(spans) == [14], "the period from the batch's whole steps: 280 ms over 14 periods of 20 ms"
    assert stalled.tolist() == [False, False, False, True, False, False]
    _, _, short = spanned(gyr, np.array([0, 20, 40, 100, 120, 140]) * 10**6, np.array([0, 6]))
    assert not short.any(), "two missing samples are made up for: no stall"


def _stalled_stream(fleet: DeviceFilters, rate_hz: float = 100.0) -> int:
    """20 s of a turning, rocking device fed to ``fleet`` in batches of 100 samples, 20 samples missing from the
    19th batch on: the filters started (the first start included)."""
    gyr, acc, mag, _ = rotating_device(seconds=20.0)
    t_ns = np.arange(len(gyr), dtype=np.int64) * round(1e9 / rate_hz)
    keep = np.ones(len(gyr), dtype=bool)
    keep[1830:1850] = False
    bounds = [0]
    for lo in range(0, len(gyr), 100):
        bounds.append(bounds[-1] + int(keep[lo : lo + 100].sum()))
    batches = len(bounds) - 1
    out = fleet.update(["imu"] * batches, list(range(batches)), bounds, t_ns[keep], gyr[keep], acc[keep], mag[keep])
    return out.restarts


def test_after_a_stall_a_filter_starts_again_or_its_heading_gate_forgets(monkeypatch):
    assert _stalled_stream(DeviceFilters()) == 2, "a device that does not swing: started again after the stall"
    monkeypatch.setattr(TurnGate, "in_swing", property(lambda gate: True))  # every device swings
    seen: list[float] = []
    monkeypatch.setattr(HeadingGate, "forget_level", lambda gate: seen.append(gate.state[_LAYOUT["seen"]]))
    assert _stalled_stream(DeviceFilters()) == 1, "a swinging device's filter goes on over the stall"
    assert len(seen) == 1 and seen[0] * 0.01 >= 5.0, "its heading gate forgets a level learnt in the seconds before"


def test_forgetting_the_level_leaves_nothing_out_until_it_is_learnt_again():
    gate = HeadingGate(0.01)
    for key, value in (("level", 0.05), ("seen", 800.0), ("run", 3.0), ("accepting", 1.0), ("samples", 850.0)):
        gate.state[_LAYOUT[key]] = value
    gate.forget_level()
    assert gate.level_deg == 0.0 and gate.state[_LAYOUT["seen"]] == 0.0 and gate.state[_LAYOUT["run"]] == 0.0
    assert gate.samples == 850, "its blocks go on as they were (the turn gate's)"
