"""Whether a held-out gain over the raw field is more than chance (magnet.quality.chance)."""

import numpy as np
import pytest

from magnet.frames import euler_to_quaternion, quaternion_to_matrix
from magnet.quality import chance, motion

RATE_HZ = 50.0
STRETCH_S = 10.0
FIT_OFFSET_UT = [0.5, 0.0, 0.0]
RAW_OFFSET_UT = [300.0, -200.0, 100.0]  # a phone's hard iron, ten times the Earth's field


def robot(turns_at_s: list[float], seconds: float = 100.0, sway_deg: float = 0.0):
    """A device that goes straight and turns by 90 deg in 3 s at each of ``turns_at_s`` (with a yaw sway of
    ``sway_deg`` at 1 Hz, a walker's): its attitude (N, 4) and the held-out rows (every fifth block of 20 samples,
    as the fits hold them out)."""
    t = np.arange(int(seconds * RATE_HZ)) / RATE_HZ
    yaw = 90.0 * sum((np.clip((t - start) / 3.0, 0.0, 1.0) for start in turns_at_s), np.zeros_like(t))
    yaw = yaw + sway_deg * np.sin(2.0 * np.pi * t)
    return euler_to_quaternion(yaw, 0.0, 0.0), (np.arange(len(t)) // 20) % 5 == 0


def departures(attitude: np.ndarray, rows: np.ndarray, offset_ut: list[float], noise_ut: float, seed: int):
    """Held-out departures (deg) of a field: the Earth's (20 uT north, 45 down) plus an offset, with noise."""
    body = np.einsum("nji,j->ni", quaternion_to_matrix(attitude), [20.0, 0.0, 45.0])
    field = body + np.asarray(offset_ut) + np.random.default_rng(seed).normal(0.0, noise_ut, body.shape)
    ev = motion.MotionEvidence(np.full(body.shape, np.nan), attitude, "fused gravity", 1.0 / RATE_HZ)
    return motion._errors_deg(field, ev, rows)


def rms(values: np.ndarray) -> float:
    return float(np.sqrt(np.mean(values**2)))


def test_two_separate_turns_pass_where_the_runs_of_time_could_pass_nothing():
    """The raw field departs by tens of deg in the turns and less than the fit on the straights: the runs of time
    hold the turns in two of ten, their spread is the raw field's whole figure, and no fit could pass; the runs of
    equal rotation and the ratio take over, and a fit 20 times better on both turns passes."""
    attitude, rows = robot([15.0, 75.0])
    turned = chance.turns(attitude, rows, 1.0 / RATE_HZ, STRETCH_S)
    assert turned is not None
    mine = departures(attitude, rows, FIT_OFFSET_UT, 0.5, 1)
    theirs = departures(attitude, rows, RAW_OFFSET_UT, 0.5, 2)
    assert chance.difference_margin(mine, theirs) == np.float64(rms(theirs))  # even a perfect fit would fail
    margin = chance.margin(mine, theirs, turned)
    assert margin is not None and rms(mine) < rms(theirs) - margin
    assert chance.margin(mine, theirs) == chance.difference_margin(mine, theirs)  # a refresh's: as before


def test_a_gain_on_a_single_turn_is_not_enough():
    attitude, rows = robot([25.0])
    turned = chance.turns(attitude, rows, 1.0 / RATE_HZ, STRETCH_S)
    assert turned is not None and len(set(turned.stretch[turned.stretch >= 0])) == 1
    mine = departures(attitude, rows, FIT_OFFSET_UT, 0.5, 1)
    theirs = departures(attitude, rows, RAW_OFFSET_UT, 0.5, 2)
    assert chance.margin(mine, theirs, turned) == rms(theirs)  # nothing passes


def test_where_the_difference_test_has_power_it_decides_alone():
    """A walker's sway turns the phone in every run of time: the difference test is not saturated, and its margin
    is the one used, whatever the runs of rotation would say."""
    attitude, rows = robot([], sway_deg=20.0)
    turned = chance.turns(attitude, rows, 1.0 / RATE_HZ, STRETCH_S)
    mine = departures(attitude, rows, FIT_OFFSET_UT, 0.5, 1)
    theirs = departures(attitude, rows, RAW_OFFSET_UT, 0.5, 2)
    by_difference = chance.difference_margin(mine, theirs)
    assert by_difference is not None and by_difference < rms(theirs)
    assert chance.margin(mine, theirs, turned) == by_difference


def test_a_small_gain_is_chance_and_no_turn_vouches_for_nothing():
    attitude, rows = robot([15.0, 75.0])
    turned = chance.turns(attitude, rows, 1.0 / RATE_HZ, STRETCH_S)
    assert turned is not None
    theirs = departures(attitude, rows, [4.0, 0.0, 0.0], 1.0, 2)
    mine = departures(attitude, rows, [3.6, 0.0, 0.0], 1.0, 3)  # 10 % less offset
    margin = chance.ratio_margin(mine, theirs, turned)
    assert margin is not None and rms(mine) > rms(theirs) - margin
    still, rows = robot([])
    none_turned = chance.turns(still, rows, 1.0 / RATE_HZ, STRETCH_S)
    assert none_turned is not None and (none_turned.stretch == -1).all()
    assert chance.ratio_margin(np.full(rows.sum(), 0.5), np.full(rows.sum(), 0.9), none_turned) == pytest.approx(0.9)


def test_too_few_rows_or_no_attitude():
    attitude, rows = robot([15.0, 75.0])
    turned = chance.turns(attitude, rows, 1.0 / RATE_HZ, STRETCH_S)
    assert chance.margin(np.ones(10), np.ones(10), turned) is None
    assert chance.turns(None, rows, 0.1, STRETCH_S) is None
    assert chance.turns(attitude, rows, None, STRETCH_S) is None


def test_a_vehicle_shows_no_walkers_steps():
    """A walker's steps vary the specific force by 2.5-3 m/s^2 at 2 Hz; a robot's bumps and a boat's waves by a few
    tenths: only the vehicle's turns may vouch for its first record."""
    t = np.arange(1000) / RATE_HZ
    rng = np.random.default_rng(4)
    still = np.column_stack([np.zeros_like(t), np.zeros_like(t), np.full_like(t, 9.81)])
    bumps = still + rng.normal(0.0, 0.2, still.shape)
    steps = still + np.column_stack([np.zeros_like(t), np.zeros_like(t), 3.5 * np.sin(2 * np.pi * 2.0 * t)])
    assert chance.vehicle(bumps, 1.0 / RATE_HZ)
    assert chance.vehicle(bumps / 9.81, 1.0 / RATE_HZ)  # in g
    assert not chance.vehicle(steps, 1.0 / RATE_HZ)
    assert not chance.vehicle(None, 1.0 / RATE_HZ)
    assert not chance.vehicle(bumps, None)
    assert not chance.vehicle(bumps[:50], 1.0 / RATE_HZ)  # not a whole window
