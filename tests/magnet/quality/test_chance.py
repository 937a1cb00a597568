"""Whether a held-out gain over the raw field is more than chance (magnet.quality.chance)."""

import numpy as np
import pytest

from magnet.frames import euler_to_quaternion, quaternion_to_matrix
from magnet.quality import chance, motion

RATE_HZ = 50.0
STRETCH_S = 10.0


def robot(turns_at_s: list[float], seconds: float = 100.0) -> tuple[np.ndarray, np.ndarray]:
    """A robot that drives straight and turns by 90 deg in 3 s at each of ``turns_at_s``: its attitude (N, 4) and
    the held-out rows (every fifth block of 20 samples, as the fits hold them out)."""
    t = np.arange(int(seconds * RATE_HZ)) / RATE_HZ
    yaw = 90.0 * sum((np.clip((t - start) / 3.0, 0.0, 1.0) for start in turns_at_s), np.zeros_like(t))
    return euler_to_quaternion(yaw, 0.0, 0.0), (np.arange(len(t)) // 20) % 5 == 0


def departures(attitude: np.ndarray, rows: np.ndarray, offset_ut: list[float], noise_ut: float, seed: int):
    """Held-out departures (deg) of a field: the Earth's (20 uT north, 45 down) plus an offset, with noise."""
    body = np.einsum("nji,j->ni", quaternion_to_matrix(attitude), [20.0, 0.0, 45.0])
    field = body + np.asarray(offset_ut) + np.random.default_rng(seed).normal(0.0, noise_ut, body.shape)
    ev = motion.MotionEvidence(np.full(body.shape, np.nan), attitude, "fused gravity", 1.0 / RATE_HZ)
    return motion._errors_deg(field, ev, rows)


def test_twenty_times_better_on_two_separate_turns_is_more_than_chance():
    """The raw field departs by tens of deg in the turns and less than the fit on the straights (the hard iron
    makes it ten times the Earth's field, so its direction is less noisy): the old test's runs of time hold the turns
    in two of ten, and it calls the gain chance; runs of equal rotation and the ratio do not."""
    attitude, rows = robot([15.0, 75.0])
    turned = chance.turns(attitude, rows, 1.0 / RATE_HZ, STRETCH_S)
    assert turned is not None
    mine = departures(attitude, rows, [0.5, 0.0, 0.0], 0.5, 1)
    theirs = departures(attitude, rows, [300.0, -200.0, 100.0], 0.5, 2)
    reference = float(np.sqrt(np.mean(theirs**2)))
    held = float(np.sqrt(np.mean(mine**2)))
    old = chance.difference_margin(mine, theirs)
    assert old is not None and held > reference - old  # chance, by the runs of time
    margin = chance.margin(mine, theirs, turned)
    assert margin is not None and held < reference - margin


def test_a_gain_on_a_single_turn_is_not_enough():
    attitude, rows = robot([25.0])
    turned = chance.turns(attitude, rows, 1.0 / RATE_HZ, STRETCH_S)
    assert turned is not None and len(set(turned.stretch[turned.stretch >= 0])) == 1
    mine = departures(attitude, rows, [0.5, 0.0, 0.0], 0.5, 1)
    theirs = departures(attitude, rows, [300.0, -200.0, 100.0], 0.5, 2)
    assert chance.ratio_margin(mine, theirs, turned) == float(np.sqrt(np.mean(theirs**2)))  # nothing passes


def test_a_small_gain_is_chance_and_no_turn_vouches_for_nothing():
    attitude, rows = robot([15.0, 75.0])
    turned = chance.turns(attitude, rows, 1.0 / RATE_HZ, STRETCH_S)
    assert turned is not None
    theirs = departures(attitude, rows, [4.0, 0.0, 0.0], 1.0, 2)
    mine = departures(attitude, rows, [3.6, 0.0, 0.0], 1.0, 3)  # 10 % less offset
    margin = chance.ratio_margin(mine, theirs, turned)
    assert margin is not None and np.sqrt(np.mean(mine**2)) > np.sqrt(np.mean(theirs**2)) - margin
    still, rows = robot([])
    none_turned = chance.turns(still, rows, 1.0 / RATE_HZ, STRETCH_S)
    assert none_turned is not None and (none_turned.stretch == -1).all()
    assert chance.margin(np.full(rows.sum(), 0.5), np.full(rows.sum(), 0.9), none_turned) == pytest.approx(0.9)


def test_too_few_rows_or_no_attitude():
    attitude, rows = robot([15.0, 75.0])
    turned = chance.turns(attitude, rows, 1.0 / RATE_HZ, STRETCH_S)
    assert chance.margin(np.ones(10), np.ones(10), turned) is None
    assert chance.turns(None, rows, 0.1, STRETCH_S) is None
    assert chance.turns(attitude, rows, None, STRETCH_S) is None
