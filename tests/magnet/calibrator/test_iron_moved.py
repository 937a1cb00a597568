"""A hard iron that moved by a few uT under the record in force is seen from the gyroscope's turns
(``magnet.calibrator.iron_moved``), and a refresh collection drops what came before (``refresh.Refresher``)."""

from __future__ import annotations

import numpy as np
import pytest

from magnet import wire
from magnet.calibrator import iron_moved
from magnet.calibrator.refresh import Refresher
from magnet.simulator import Disturbances, HardIronChange, SensorErrors, SimulatorConfig, Trajectory, simulate

STEP_S = 30.0


def _walk(step_ut: float, seed: int = 2, disturbed: bool = False):
    errors = SensorErrors.phone(np.random.default_rng([seed, 26]), 50.0)
    direction = np.array([1.0, -1.0, 1.0]) / np.sqrt(3.0)
    change = HardIronChange(STEP_S, errors.hard_iron_ut + step_ut * direction) if step_ut else None
    config = SimulatorConfig(
        trajectory=Trajectory.WALK_HAND,
        count=3000,
        errors=errors,
        seed=seed,
        hard_iron_change=change,
        disturbances=Disturbances() if disturbed else None,
    )
    return simulate(config), errors.true_calibration(50.0)


def _moved_times(run, record, until_s: float) -> list[float]:
    """The times (s) at which a watch fed the run block by block says the iron moved."""
    watch, field = iron_moved.IronWatch(), record.apply(run.mag_ut)
    t_ns = np.round(run.t_s * 1e9).astype(np.int64)
    ends = range(100, int(until_s * 50), 25)  # a batch of 25 samples at a time
    return [float(run.t_s[end - 1]) for end in ends if watch.add(field[:end], run.gyr_rads[:end], t_ns[:end], 0.02)]


def test_a_step_of_3_ut_is_seen_within_10_s_and_not_before():
    run, record = _walk(3.0)
    found = _moved_times(run, record, 60.0)
    assert found and STEP_S < found[0] < STEP_S + 10.0, found


@pytest.mark.parametrize("disturbed", [False, True])
def test_an_unchanged_iron_is_not_seen_as_moved_even_past_steel_doors(disturbed):
    run, record = _walk(0.0, seed=3, disturbed=disturbed)
    assert _moved_times(run, record, 60.0) == []


def test_the_refresh_collection_drops_what_came_before_the_move():
    run, record = _walk(3.0)
    refresher = Refresher("auto", 2000, 10)
    changed_at = None
    for seq, start in enumerate(range(0, len(run.t_s), 25)):
        part = slice(start, start + 25)
        t_ns = np.round(run.t_s[part] * 1e9).astype(np.int64) + 10**18
        batch = wire.RawBatch(
            "phone", seq, "sim", t_ns, run.mag_ut[part], run.acc_ms2[part], gyr_rads=run.gyr_rads[part]
        )
        collection = refresher.receive(batch, record)
        if collection is not None and collection.after_change and changed_at is None:
            changed_at = float(run.t_s[part][-1])
    assert changed_at is not None and STEP_S < changed_at < STEP_S + 12.0
