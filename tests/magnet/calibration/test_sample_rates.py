"""The fits at the rates phones record at (docs/field-calibration.md, "Sample rates"): what is judged in time is
counted in seconds, so that a motion sampled at 100 or 200 Hz is judged as at the bench's 50 Hz."""

from __future__ import annotations

import numpy as np
import pytest

from magnet.calibration import HOLDOUT_BLOCK, HOLDOUT_BLOCK_S, FitInput
from magnet.calibration.base import holdout_mask
from magnet.calibration.choose import fit_choice
from magnet.simulator import SensorErrors, SimulatorConfig, Trajectory, simulate

SEED = 4  # a tuning seed: its texting walk's first corner comes at 12-13.5 s


def _held_out_times(rate_hz: float, seconds: float) -> np.ndarray:
    count = int(seconds * rate_hz)
    return np.flatnonzero(holdout_mask(count, 1.0 / rate_hz)) / rate_hz


def test_held_out_blocks_fall_at_the_same_moments_at_every_rate() -> None:
    at_50 = _held_out_times(50.0, 20.0)
    for rate in (25.0, 100.0, 200.0):
        times = _held_out_times(rate, 20.0)
        # the same blocks of time: every time held out at this rate lies in a block held out at 50 Hz
        assert np.all(np.isin(np.floor(times * 50.0 + 1e-9).astype(int), np.round(at_50 * 50.0).astype(int)))
        assert len(times) / rate == pytest.approx(len(at_50) / 50.0)
    assert round(HOLDOUT_BLOCK_S * 50.0) == HOLDOUT_BLOCK  # at 50 Hz the blocks are what they were
    assert np.array_equal(holdout_mask(1000, 0.02), holdout_mask(1000))


@pytest.mark.parametrize("rate_hz", [50.0, 100.0, 200.0])
def test_a_texting_walk_gets_its_first_record_as_soon_at_every_rate(rate_hz: float) -> None:
    """The first 13.5 s of a texting walk (the calibrator's fit at that moment): accepted, offset within 3 uT, at 50
    Hz and, since the held-out blocks are in seconds, at 100 and 200 Hz (refused before: held out every 20 samples,
    the 100 Hz judgement saw the corner at 12-13.5 s that the 50 Hz one did not, and called the gain chance)."""
    rng = np.random.default_rng([SEED, 26])
    errors = SensorErrors.phone(rng, 50.0)
    config = SimulatorConfig(
        trajectory=Trajectory.WALK_TEXTING, rate_hz=rate_hz, count=int(13.48 * rate_hz), errors=errors, seed=SEED
    )
    run = simulate(config)
    earth = run.earth
    data = FitInput(
        run.mag_ut,
        t_s=run.t_s,
        acc=run.acc_ms2,
        gyr_rads=run.gyr_rads,
        period_s=1.0 / rate_hz,
        field_ut=earth.total_ut,
        dip_deg=earth.inclination_deg,
        declination_deg=earth.declination_deg,
    )
    record = fit_choice(data, "auto")
    assert record.accepted, record.reason
    assert np.linalg.norm(np.asarray(record.offset) - errors.hard_iron_ut) < 3.0
