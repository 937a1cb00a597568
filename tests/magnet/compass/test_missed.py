"""Samples missing within a batch (``magnet.compass.missed``): the sample after them turns the filter over their time
and the batch's period counts them, so a phone that drops 2 % of its samples keeps its heading."""

from __future__ import annotations

import numpy as np
from compass_steps import WALL_NS, heading_errors_deg

from magnet import wire
from magnet.compass.missed import spanned
from magnet.simulator import SensorErrors, SimulatorConfig, Trajectory, simulate


def test_whole_missing_steps_are_counted_and_jitter_is_not():
    t_ns = np.array([0, 20, 40, 80, 100, 1000, 1021, 1039, 1061, 1080]) * 10**6
    gyr = np.ones((10, 3))
    edges = np.array([0, 5, 10])
    scaled, spans = spanned(gyr, t_ns, edges)
    np.testing.assert_array_equal(scaled[:, 0], [1, 1, 1, 2, 1, 1, 1, 1, 1, 1])
    np.testing.assert_array_equal(spans, [5, 4])
    uniform, spans = spanned(gyr, np.arange(10) * 20 * 10**6, edges)
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
