"""HMC5883L self-test maths (seed 003 figures) and its property: the scale factors undo a per-axis gain error."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from magnet.drivers.selftest import evaluate, expected_counts, limits_counts, temperature_factor, to_calibration


def test_seed_figures():
    assert np.allclose(expected_counts(3), [765.6, 765.6, 712.8])  # seed: about 766 and 713 at GN=3
    assert limits_counts(5) == (243.0, 575.0)  # datasheet limits at GN=5
    result = evaluate([750, 766, 713], [-750, -766, -713], 3)
    assert result.passed and result.scale[0] == pytest.approx(765.6 / 750)
    assert temperature_factor([750, 750, 700], [700, 750, 700]) == pytest.approx([750 / 700, 1, 1])


def test_failures_are_reported_per_axis():
    result = evaluate([452, 100, 421], [-452, -100, -421], 5)
    assert not result.passed and list(result.axis_passed) == [True, False, True]
    assert np.isnan(result.scale[1]) and "axis y" in result.message
    overflow = evaluate([452, -4096, 421], [-452, -452, -421], 5)
    assert not overflow.passed and "higher GN" in overflow.message
    with pytest.raises(ValueError, match="failed self-test"):
        to_calibration(result)
    with pytest.raises(ValueError, match=r"GN must be 0..7"):
        evaluate([1, 1, 1], [1, 1, 1], 8)


@settings(max_examples=30, deadline=None)
@given(
    st.integers(0, 7),
    st.lists(st.floats(-0.25, 0.25), min_size=3, max_size=3),
    st.lists(st.floats(-30, 30), min_size=3, max_size=3),
)
def test_scale_undoes_gain_error_whatever_the_offset(gain, error, offset):
    error = np.array(error)
    true_bias = expected_counts(gain)
    positive = true_bias * (1 + error) + offset  # a residual offset cancels in (p - n) / 2
    negative = -true_bias * (1 + error) + offset
    result = evaluate(positive, negative, gain)
    low, high = limits_counts(gain)
    inside = (positive >= low) & (positive <= high) & (-negative >= low) & (-negative <= high)
    assert np.array_equal(result.axis_passed, inside)
    assert np.allclose(result.scale[inside] * (1 + error[inside]), 1.0)
    if result.passed:
        calibration = to_calibration(result)
        assert np.allclose(calibration.apply(true_bias * (1 + error)), true_bias)
