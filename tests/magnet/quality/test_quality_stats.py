"""The fast forms of magnet.quality.stats give numpy's numbers: the median bit for bit (NaN included), the same rows
as boolean indexing, the covariance to the last digits; and the benchmark's samples are a real ellipsoid."""

from __future__ import annotations

import numpy as np
import pytest

from magnet.calibration import FitInput, fit
from magnet.quality.stats import column_medians, covariance, median, take_rows
from services.bench.fit import synthetic_tumble


@pytest.mark.parametrize("count", [1, 2, 3, 4, 7, 10, 101, 1000])
def test_median_is_numpys_bit_for_bit(count):
    rng = np.random.default_rng(count)
    for trial in range(20):
        values = rng.normal(size=count) * 10.0 ** rng.uniform(-3, 3)
        if trial % 3 == 1:
            values = np.round(values)  # ties
        assert median(values) == float(np.median(values))
    rows = rng.normal(size=(count, 3))
    np.testing.assert_array_equal(column_medians(rows), np.median(rows, axis=0))


def test_median_of_nan_is_nan_and_of_nothing_an_error():
    assert np.isnan(median(np.array([1.0, np.nan, 3.0, 4.0])))
    with pytest.raises(ValueError, match="no values"):
        median(np.array([]))


def test_take_rows_and_covariance_match_numpy():
    rng = np.random.default_rng(0)
    points = rng.normal(size=(500, 3)) * [1.0, 20.0, 300.0] + 40.0
    mask = rng.random(500) < 0.3
    np.testing.assert_array_equal(take_rows(points, mask), points[mask])
    np.testing.assert_allclose(covariance(points), np.cov(points, rowvar=False), rtol=1e-13, atol=0)


def test_the_benchmark_tumble_is_an_ellipsoid_that_the_fit_accepts():
    raw, acc = synthetic_tumble(2000, 0)  # |B| constant: north and down from the same rotation
    calibration = fit(FitInput(raw, acc=acc), "ellipsoid+align")
    assert calibration.accepted, calibration.reason
    assert calibration.quality["residual_rms_ut"] < 0.5  # the noise is 0.3 uT
    np.testing.assert_allclose(calibration.offset, [60.0, -120.0, 35.0], atol=0.1)
    assert "misalignment 5.0" in calibration.reason
