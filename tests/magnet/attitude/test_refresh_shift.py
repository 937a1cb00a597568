"""A refresh that hardly moves the field moves the causal filter's heading at once (``magnet.attitude.refresh_shift``):
a walk's compass with a record 3 uT off, then the right one, heads as one that had the right one all along, where
vqf's loop alone (tauMag) carried the old error on."""

from __future__ import annotations

import numpy as np
import pytest
from compass_steps import WALL_NS, heading_errors_deg

from magnet import wire
from magnet.attitude import refresh_shift
from magnet.compass.calibrations import small_change
from magnet.simulator import SensorErrors, SimulatorConfig, Trajectory, simulate

DEVICE = "phone"
FIRST_S, SWITCH_S = 10.0, 35.0


@pytest.fixture(scope="module")
def walk():
    errors = SensorErrors.phone(np.random.default_rng([3, 26]), 50.0)
    config = SimulatorConfig(trajectory=Trajectory.WALK_TEXTING, count=2500, errors=errors, seed=3)
    run = simulate(config)
    right = errors.true_calibration(run.earth.total_ut)
    wrong = right.replace(offset=right.offset + np.array([2.0, -2.0, 1.0]))
    assert small_change(wrong, right)  # a refresh the filter keeps running through
    return run, wrong, right


def _after(run, error: np.ndarray) -> float:
    """Mean error (deg) over the 3 s after the switch."""
    return float(np.mean(error[(run.t_s >= SWITCH_S) & (run.t_s < SWITCH_S + 3.0)]))


def test_a_refresh_moves_the_heading_at_once(walk, monkeypatch):
    run, wrong, right = walk
    one = [(FIRST_S, wire.encode_calibration(DEVICE, right, WALL_NS))]
    two = [(FIRST_S, wire.encode_calibration(DEVICE, wrong, WALL_NS))]
    two.append((SWITCH_S, wire.encode_calibration(DEVICE, right, WALL_NS + 1)))
    always = _after(run, heading_errors_deg(run, one))
    shifted = _after(run, heading_errors_deg(run, two))
    monkeypatch.setattr(refresh_shift, "ENABLED", False)
    loop_only = _after(run, heading_errors_deg(run, two))
    assert abs(shifted - always) < 0.5, (shifted, always)
    assert abs(loop_only - always) > 1.5, (loop_only, always)
