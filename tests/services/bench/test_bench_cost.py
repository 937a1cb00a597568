"""``magnet bench cost``: its log and its stages (the figures themselves are the benchmark's to print, not tested)."""

from __future__ import annotations

import sys

import numpy as np
import pytest

from services.bench import cost
from services.common.inputs.csvio import read_samples


def test_log_csv_is_what_magnet_heading_and_the_floor_read(tmp_path):
    log = cost.simulated_log(0.05, cost.RATE_HZ)
    path = tmp_path / "log.csv"
    cost.write_log_csv(path, log, velocity=True)
    table = read_samples(path)
    np.testing.assert_allclose(table.mag, log.mag_ut, rtol=1e-8)
    vel = table.vel_ned_ms()
    assert vel is not None and np.isnan(vel[0]).all()  # no fix yet at the first sample
    changes = np.any(np.diff(vel[np.isfinite(vel[:, 0])], axis=0) != 0, axis=1)
    assert changes.mean() > 0.9  # a new fix on (almost) every row
    floor = np.loadtxt(path, delimiter=",", skiprows=1)
    np.testing.assert_allclose(floor[:, 7:10], log.gyr_rads, rtol=1e-8)  # the floor's columns are the gyroscope's


def test_every_stage_is_timed_beside_vqf_where_it_runs_vqf():
    rows = cost.stage_costs(cost.simulated_log(0.05, cost.LIVE_FIX_HZ))
    names = [name for name, _, _ in rows]
    for stage in ("decode", "calibration", "tilt", "fusion", "encode", "ROS 2"):
        assert stage in names
    assert any(name.startswith("aided fusion") for name in names)
    assert all(us > 0 for _, us, _ in rows)
    assert {name for name, _, own in rows if own is not None} >= {"fusion"}


def test_the_median_of_pairs_is_the_middle_value_or_the_mean_of_the_two():
    assert cost._median([3.0, 1.0, 2.0]) == 2.0
    assert cost._median([4.0, 1.0, 3.0, 2.0]) == 2.5


@pytest.mark.integration  # starts processes
def test_pairs_of_processes_are_timed_in_turn():
    pairs = cost.process_pairs([sys.executable, "-c", "pass"], [sys.executable, "-c", "pass"], pairs=2)
    assert len(pairs) == 2 and all(a > 0 and b > 0 for a, b in pairs)
