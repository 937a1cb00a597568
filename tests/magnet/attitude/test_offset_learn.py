"""The record's offset error learnt in service against the gyroscope (``magnet.attitude.offset_learn``): a texting
walk's compass with a record 2 uT off finds that error from the turns (within a few tenths of a uT on the horizontal
axes, where the turns show it) and heads closer to one with the right record than without the learner."""

from __future__ import annotations

import numpy as np
import pytest
from compass_steps import WALL_NS, heading_errors_deg

from magnet import wire
from magnet.attitude import offset_learn
from magnet.simulator import SensorErrors, SimulatorConfig, Trajectory, simulate

DEVICE = "phone"
FIRST_S = 10.0
#: the raw offset's error given to the record (uT, sensor axes x forward, y right, z down)
WRONG_UT = np.array([1.5, -1.5, 0.5])


@pytest.fixture(scope="module")
def walk():
    errors = SensorErrors.phone(np.random.default_rng([5, 26]), 50.0)
    config = SimulatorConfig(trajectory=Trajectory.WALK_TEXTING, count=6000, errors=errors, seed=5)
    run = simulate(config)
    right = errors.true_calibration(run.earth.total_ut)
    wrong = right.replace(offset=right.offset + WRONG_UT)
    return run, right, wrong


def _records(calibration) -> list[tuple[float, bytes]]:
    return [(FIRST_S, wire.encode_calibration(DEVICE, calibration, WALL_NS))]


def _scatter(run, error: np.ndarray) -> float:
    """RMS (deg) of the heading error about its mean over the last 40 s."""
    late = error[run.t_s >= run.t_s[-1] - 40.0]
    return float(np.sqrt(np.nanmean((late - np.nanmean(late)) ** 2)))


def test_the_learner_finds_the_record_offset_error(walk, monkeypatch):
    run, _, wrong = walk
    found = []
    move_to = offset_learn.OffsetLearner.move_to

    def spy(self, offset_ut):
        found.append(np.array(offset_ut))
        return move_to(self, offset_ut)

    monkeypatch.setattr(offset_learn.OffsetLearner, "move_to", spy)
    heading_errors_deg(run, _records(wrong))
    assert found, "the learner never fitted"
    # the corrected field is A (u - b - d) = right - A d (sensor axes), in vqf's body axes (y, z turned)
    truth = -(wrong.matrix @ WRONG_UT) * np.array([1.0, -1.0, -1.0])
    assert np.all(np.abs(found[-1][:2] - truth[:2]) < 0.5), (found[-1], truth)


def test_the_heading_with_a_wrong_record_comes_closer_to_the_right_one(walk, monkeypatch):
    run, right, wrong = walk
    learnt = _scatter(run, heading_errors_deg(run, _records(wrong)))
    monkeypatch.setattr(offset_learn, "ENABLED", False)
    without = _scatter(run, heading_errors_deg(run, _records(wrong)))
    best = _scatter(run, heading_errors_deg(run, _records(right)))
    assert learnt < without - 0.2, (learnt, without, best)
    assert learnt < best + 0.3, (learnt, without, best)


def test_take_off_leaves_rows_without_a_field():
    class Fusion:
        aided = False
        _filter = object()

    class State:
        filter = Fusion()

    state = State()
    learner = offset_learn.OffsetLearner.__new__(offset_learn.OffsetLearner)
    learner.filter, learner.offset_ut = state.filter._filter, np.array([1.0, -2.0, 0.5])
    state.offset = learner
    field = np.array([[10.0, 0.0, -40.0], [0.0, 0.0, 0.0], [20.0, 5.0, -40.0], [1.0, 1.0, 1.0]])
    offset_learn.take_off(state, field, 0, 3)
    assert np.allclose(field, [[9.0, 2.0, -40.5], [0.0, 0.0, 0.0], [19.0, 7.0, -40.5], [1.0, 1.0, 1.0]])
