"""The first heading after a start is not taken from a field away from the record's strength (a door, a car by the
device while vqf takes its heading as a mean of its first seconds): those samples are left out, and the take starts
again once the field is back (``magnet.compass.first_heading``)."""

from __future__ import annotations

import numpy as np
import pytest
from compass_steps import compass_core
from fusion_helpers import FIELD_NED_UT, RATE_HZ, rotating_device
from test_compass_fusion import batches, joined, run_compass

from magnet import frames, wire
from magnet.attitude import fusion
from magnet.attitude.heading import HeadingFlag, angle_difference_deg
from magnet.compass.first_heading import CALM_S, MIN_JUDGED_S, FirstHeading, expected_columns
from magnet.earth.expected import Earth
from magnet.model import Calibration

STRENGTH_UT = float(np.linalg.norm(FIELD_NED_UT))
#: a steel door's field by the device (NED uT) from DOOR_S[0] to DOOR_S[1] seconds after the start
DOOR_NED_UT = np.array([45.0, 50.0, -20.0])
DOOR_S = (1.0, 2.5)


def _take(period_s: float = 0.01) -> FirstHeading:
    take = FirstHeading()
    take.start(fusion.Fusion(period_s))
    return take


def _fields(strengths_ut: np.ndarray) -> np.ndarray:
    return np.column_stack([strengths_ut, np.zeros((len(strengths_ut), 2))])


def _door_walk() -> np.ndarray:
    """|B| (S,) over 9 s at 100 Hz: the Earth's, a door's stronger field on samples 100 .. 249."""
    strengths = np.full(900, STRENGTH_UT)
    strengths[100:250] = 2.4 * STRENGTH_UT
    return strengths


def _judged_in(take: FirstHeading, fields: np.ndarray, expected: np.ndarray, size: int) -> tuple[np.ndarray, int]:
    """The samples left out (S,) and where the take starts again, judging ``size`` samples at a time."""
    left_out, lo = np.zeros(len(fields), dtype=bool), 0
    while lo < len(fields):
        hi = min(len(fields), lo + size)
        out, again = take.judge(fields, expected, lo, hi)
        stop = hi if again is None else lo + again
        if out is not None:
            left_out[lo:stop] = out[: stop - lo]
        if again is not None:
            return left_out, stop
        lo = stop
    return left_out, -1


@pytest.mark.parametrize("size", [900, 7, 50])
def test_the_door_is_left_out_and_the_take_starts_again_after_it_however_batched(size):
    fields, expected = _fields(_door_walk()), np.full(900, STRENGTH_UT)
    left_out, again = _judged_in(_take(), fields, expected, size)
    assert np.flatnonzero(left_out).tolist() == list(range(100, 250))
    given = fields.any(axis=1)
    assert not given[100:250].any() and given[:100].all() and given[250:].all(), "their field zeroed, no other"
    assert again == 249 + round(CALM_S * RATE_HZ), "a second of the Earth's field after the door's last sample"


def test_nothing_is_left_out_when_the_field_is_the_earths_or_no_strength_is_known():
    fields = _fields(np.full(900, STRENGTH_UT * 1.1))
    assert _take().judge(fields, np.full(900, STRENGTH_UT), 0, 900) == (None, None)
    door = _fields(_door_walk())
    assert _take().judge(door, np.full(900, np.nan), 0, 900) == (None, None)
    assert door.any(axis=1).all(), "unknown strength: nothing zeroed"


@pytest.mark.parametrize("size", [900, 50])
def test_a_strength_the_field_never_has_is_in_question_not_the_field(size):
    fields = _fields(np.full(900, STRENGTH_UT * 1.6))  # another place, another scale: every sample away
    left_out, again = _judged_in(_take(), fields, np.full(900, STRENGTH_UT), size)
    assert again == -1
    assert left_out.sum() <= MIN_JUDGED_S * RATE_HZ, "given up within its few seconds"
    assert fields[int(MIN_JUDGED_S * RATE_HZ) :].any(axis=1).all(), "and the rest reaches the filter"


def test_the_take_is_over_after_tau_mag():
    take = _take()
    calm = _fields(np.full(2000, STRENGTH_UT))
    assert take.judge(calm, np.full(2000, STRENGTH_UT), 0, 2000) == (None, None)
    door = _fields(_door_walk())
    assert take.judge(door, np.full(900, STRENGTH_UT), 0, 900) == (None, None), "vqf's first heading is taken"
    assert door.any(axis=1).all()


def test_the_expected_strength_is_the_records_own_else_the_models_and_none_uncalibrated():
    own = wire.DeviceCalibration("a", 1, Calibration("ellipsoid", np.zeros(3), np.eye(3), field_strength=48.0))
    gauss = wire.DeviceCalibration("b", 1, Calibration("ellipsoid", np.zeros(3), np.eye(3), field_strength=0.5,
                                                       output_unit="gauss"))  # fmt: skip
    stated_none = wire.DeviceCalibration("c", 1, Calibration("ellipsoid", np.zeros(3), np.eye(3)))
    expected = expected_columns([own, gauss, stated_none, None], [2, 1, 1, 1], np.full(5, 51.0))
    np.testing.assert_allclose(expected[:4], [48.0, 48.0, 50.0, 51.0])
    assert np.isnan(expected[4])


def _walk_by_a_door():
    gyr, acc, mag, truth = rotating_device(seconds=20.0)
    t_s = np.arange(len(gyr)) / RATE_HZ
    door = (t_s >= DOOR_S[0]) & (t_s < DOOR_S[1])
    rotation = frames.quaternion_to_matrix(truth)
    mag = mag.copy()
    mag[door] += np.einsum("nji,j->ni", rotation[door], DOOR_NED_UT)  # fixed in the world, seen in the body
    return (gyr, acc, mag, truth), t_s


def test_a_compass_starting_by_a_door_takes_its_heading_from_the_earths_field():
    device, t_s = _walk_by_a_door()
    record = wire.DeviceCalibration("imu-1", 1, Calibration("ellipsoid", np.zeros(3), np.eye(3), field_strength=50.0))
    core = compass_core(Earth(total_ut=50.0), window=1)
    core.accept_calibration(wire.pack(record.to_record()), "magnet/imu-1/calibration", "magnet")
    out = run_compass(core, batches(device))
    heading, flags = joined(out, "heading_deg"), joined(out, "flags")
    true_heading, pitch, _ = frames.quaternion_to_euler(device[3])
    error = np.abs(angle_difference_deg(heading, true_heading))
    after = (t_s > 4.0) & (t_s < 12.0) & (np.abs(pitch) < 60)
    assert np.sqrt(np.mean(error[after] ** 2)) < 2.0, "the door's heading was not taken"
    door = (t_s >= DOOR_S[0]) & (t_s < DOOR_S[1])
    assert np.mean(flags[door] & HeadingFlag.FIELD_DISTURBED > 0) > 0.9, "its samples are flagged disturbed"


def test_a_door_late_in_the_take_is_left_out_without_taking_again():
    strengths = np.full(900, STRENGTH_UT)
    strengths[500:650] = 2.4 * STRENGTH_UT  # most of the heading was taken before it: taking again would only lag
    fields = _fields(strengths)
    left_out, again = _judged_in(_take(), fields, np.full(900, STRENGTH_UT), 50)
    assert np.flatnonzero(left_out).tolist() == list(range(500, 650))
    assert again == -1


def test_a_door_from_the_first_sample_is_not_left_out_but_the_take_starts_again_after_it():
    strengths = np.full(900, STRENGTH_UT)
    strengths[:150] = 1.4 * STRENGTH_UT  # from the start: nothing yet said the strength is the Earth's
    fields = _fields(strengths)
    left_out, again = _judged_in(_take(), fields, np.full(900, STRENGTH_UT), 50)
    assert not left_out.any() and fields.any(axis=1).all()
    assert again == 149 + round(CALM_S * RATE_HZ)
