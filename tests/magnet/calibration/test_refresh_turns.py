"""A travelling level device's refresh judged by its field's turn against the gyroscope's where the held-out heading
consistency refused it (``magnet.calibration.turning.judged_by_turns``; docs/field-calibration.md, "A vehicle's
refresh judged by its turns"). The motion is the simulator's boat (tuning seed 1, 43 s of turns at 8-15 deg/s)."""

from __future__ import annotations

import numpy as np
import pytest
from fusion_helpers import phone_boat

from magnet.calibration import turning
from magnet.model import Calibration
from magnet.simulator import SimulatedRun

RATE_HZ = 50.0
HARD_IRON_UT = np.array([30.0, -20.0, 45.0])


@pytest.fixture(scope="module")
def boat() -> tuple[SimulatedRun, np.ndarray, turning.Turns]:
    run = phone_boat(43.0, RATE_HZ)
    raw = run.true_field_ut + np.random.default_rng(3).normal(0.0, 0.5, run.true_field_ut.shape) + HARD_IRON_UT
    windows = turning.turns(run.gyr_rads, 1.0 / RATE_HZ)
    assert windows is not None
    return run, raw, windows


def _record(offset_error_ut: float, accepted: bool = False) -> Calibration:
    return Calibration(
        method="offset",
        offset=HARD_IRON_UT + np.array([offset_error_ut, 0.0, 0.0]),
        matrix=np.eye(3),
        field_strength=50.0,
        sample_count=2000,
        unit="ut",
        output_unit="ut",
        accepted=accepted,
        reason="refused: not more constant than the calibration in force by more than chance",
        quality={
            "residual_rms_ut": 0.6,
            "residual_rms_pct": 1.2,
            "holdout_consistency_deg": 1.6,
            "reference_holdout_consistency_deg": 1.65,
            "why": "offset",
        },
    )


def _turned(record: Calibration, raw: np.ndarray, windows: turning.Turns) -> Calibration:
    return turning.with_turn_residual(record, windows, raw)


def test_a_refresh_that_turns_with_the_gyroscope_better_is_accepted(boat) -> None:  # type: ignore[no-untyped-def]
    _, raw, windows = boat
    refresh = _turned(_record(0.0), raw, windows)
    judged = turning.judged_by_turns(refresh, windows, raw, _record(2.5, accepted=True))
    assert judged.accepted, judged.reason
    assert judged.quality.get("judged_by") == turning.JUDGED_BY
    assert judged.quality.get("turn_gain_pct") > 100 * turning.REFRESH_TURN_GAIN
    assert judged.quality.get("reference_turn_residual_ut") > judged.quality.get("turn_residual_ut")


def test_a_refresh_that_turns_worse_stays_refused(boat) -> None:  # type: ignore[no-untyped-def]
    _, raw, windows = boat
    refresh = _turned(_record(2.5), raw, windows)
    judged = turning.judged_by_turns(refresh, windows, raw, _record(0.0, accepted=True))
    assert not judged.accepted
    assert "turns with the gyroscope only" in judged.reason
    assert judged.quality.get("turn_gain_pct") < 0


def test_accepted_records_and_other_devices_are_left_as_they_are(boat) -> None:  # type: ignore[no-untyped-def]
    _, raw, windows = boat
    accepted = _turned(_record(0.0, accepted=True), raw, windows)
    assert turning.judged_by_turns(accepted, windows, raw, _record(2.5, accepted=True)) is accepted
    refused = _turned(_record(0.0), raw, windows)
    assert turning.judged_by_turns(refused, None, raw, _record(2.5, accepted=True)) is refused  # no velocity
    assert turning.judged_by_turns(refused, windows, raw, None) is refused  # a first record: nothing in force
