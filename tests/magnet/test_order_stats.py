"""``magnet.order_stats`` gives numpy's numbers bit for bit: the quantile as ``np.quantile`` (its default, linear,
method) and ``np.nanquantile`` on the values without NaN, infinities and ties included; the median's own tests are in
``tests/magnet/quality/test_quality_stats.py``."""

from __future__ import annotations

import warnings

import numpy as np
import pytest

from magnet.order_stats import median, quantile


def _same(a: float, b: float) -> bool:
    return a == b or (np.isnan(a) and np.isnan(b))


@pytest.mark.parametrize("count", [1, 2, 3, 4, 5, 10, 33, 101, 1000])
def test_quantile_is_numpys_bit_for_bit(count):
    rng = np.random.default_rng(count)
    for trial in range(30):
        values = rng.normal(size=count) * 10.0 ** rng.uniform(-3, 3)
        if trial % 3 == 1:
            values = np.round(values)  # ties
        if trial % 7 == 2:
            values[rng.integers(count)] = np.inf
        if trial % 11 == 3:
            values[rng.integers(count)] = -np.inf
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)  # inf - inf, in numpy's lerp as in ours
            for q in (0.0, 0.1, 0.25, 0.5, 0.75, 0.9, 1.0, float(rng.uniform())):
                assert _same(quantile(values, q), float(np.quantile(values, q))), (count, trial, q)
            gaps = values.copy()
            gaps[rng.random(count) < 0.3] = np.nan
            if not np.isnan(gaps).all():
                assert _same(quantile(gaps[~np.isnan(gaps)], 0.75), float(np.nanquantile(gaps, 0.75)))


def test_quantile_of_nan_is_nan_and_of_nothing_or_beyond_0_1_an_error():
    assert np.isnan(quantile(np.array([1.0, np.nan, 3.0]), 0.5))
    assert quantile(np.array([4.0, 1.0, 3.0, 2.0]), 0.5) == median(np.array([4.0, 1.0, 3.0, 2.0])) == 2.5
    with pytest.raises(ValueError, match="no values"):
        quantile(np.array([]), 0.5)
    with pytest.raises(ValueError, match=r"within 0 \.\. 1"):
        quantile(np.array([1.0]), 1.5)
