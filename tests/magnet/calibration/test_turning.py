"""The field's turn against the gyroscope's (``magnet.calibration.turning``; docs/field-calibration.md, "The field's
turn against the gyroscope's"), and the candidates' choice by it (``magnet.calibration.candidates.best``).

The motion is the simulator's boat (tuning seed 1, a phone-like sensor, 43 s of turns at 8-15 deg/s)."""

from __future__ import annotations

import numpy as np
import pytest
from fusion_helpers import phone_boat

from magnet.calibration import candidates, turning
from magnet.calibration.candidates import SPHERE, best
from magnet.calibration.ladder import RungFit
from magnet.calibration.rungs import LEVEL_OFFSET
from magnet.model import Calibration
from magnet.simulator import SimulatedRun

RATE_HZ = 50.0
SECONDS = 43.0


@pytest.fixture(scope="module")
def boat() -> SimulatedRun:
    return phone_boat(SECONDS, RATE_HZ)


def _true_field(run: SimulatedRun, offset_error_ut: np.ndarray | None = None) -> np.ndarray:
    """The field a correction gives: the true one (the sensor's own noise kept), or with an offset error."""
    field = run.true_field_ut
    noise = np.random.default_rng(5).normal(0.0, 0.5, field.shape)
    return field + noise + (0.0 if offset_error_ut is None else offset_error_ut)


def test_a_field_off_across_the_turns_turns_worse_than_the_true_one(boat: SimulatedRun) -> None:
    windows = turning.turns(boat.gyr_rads, 1.0 / RATE_HZ)
    assert windows is not None
    right = turning.turn_residual_ut(windows, _true_field(boat))
    off = turning.turn_residual_ut(windows, _true_field(boat, np.array([2.0, 0.0, 0.0])))
    assert right < 0.85  # the noise of two samples 0.5 uT each (0.71) and the gyroscope's
    assert off > 1.15 * right


def test_the_gyroscope_bias_is_fitted_in_the_axes_the_body_had(boat: SimulatedRun) -> None:
    """With the phone's bias (up to 0.5 deg/s per axis) and windows of a quarter turn, the true field turns as the
    biased gyroscope says once the bias is fitted as integrated in the turning axes; as dt I it would not be."""
    field = _true_field(boat)
    truth = turning.turns(boat.true_gyr_rads, 1.0 / RATE_HZ)
    biased = turning.turns(boat.true_gyr_rads + np.radians([0.5, -0.5, 0.4]), 1.0 / RATE_HZ)
    assert truth is not None and biased is not None
    plain = turning.Turns(
        biased.starts,
        biased.ends,
        biased.back,
        ((biased.ends - biased.starts) / RATE_HZ)[:, None, None] * np.eye(3)[None],
    )
    fitted = turning.turn_residual_ut(biased, field)
    assert fitted < 1.05 * turning.turn_residual_ut(truth, field)
    assert turning.turn_residual_ut(plain, field) > 1.1 * fitted


def test_too_few_turns_give_no_windows() -> None:
    still = np.zeros((500, 3))
    assert turning.turns(still, 0.02) is None


def _record(turn_ut: float, consistency_deg: float, sphere: bool = False) -> tuple[RungFit, Calibration]:
    record = Calibration(
        method="offset",
        offset=np.zeros(3),
        matrix=np.eye(3),
        field_strength=50.0,
        sample_count=1000,
        unit="ut",
        output_unit="ut",
        accepted=True,
        reason="ok",
        quality={"turn_residual_ut": turn_ut, "holdout_heading_consistency_deg": consistency_deg},
    )
    fit = RungFit(SPHERE if sphere else LEVEL_OFFSET, np.zeros(3), np.eye(3), 45.0, 1.0, (), {}, 1000)
    return fit, record


def test_the_candidate_whose_field_turns_with_the_gyroscope_is_chosen() -> None:
    rung, sphere = _record(0.75, 3.0), _record(0.90, 2.0, sphere=True)
    chosen = best([rung, sphere])
    assert chosen.quality.get("turn_residual_ut") == 0.75  # held-out consistency alone would have taken the other
    assert "turn against the gyroscope" in chosen.reason
    better = best([_record(0.80, 2.0), _record(0.70, 2.0, sphere=True)])
    assert better.quality.get("turn_residual_ut") == 0.70
    close = best([_record(0.80, 2.0), _record(0.78, 1.0, sphere=True)])
    assert close.quality.get("turn_residual_ut") == 0.80  # within TURN_GAIN: the richest rung stays
    assert candidates.TURN_GAIN > 0.02
