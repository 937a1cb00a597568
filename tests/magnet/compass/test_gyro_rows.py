"""The compass filters' per-sample checks compiled (``magnet._kernels.gyro_rows``) against the numpy they replaced,
on random rows with NaN, infinite, absent and saturated values."""

from __future__ import annotations

import numpy as np

from magnet import _kernels
from magnet.compass.filters import GYRO_LIMIT_RADS


def _plainly(gyr, acc, field):
    isnan = np.isnan(gyr)
    present = ~(isnan[:, 0] & isnan[:, 1] & isnan[:, 2])
    finite = np.isfinite(gyr).all(axis=1)
    beyond = np.abs(gyr) >= GYRO_LIMIT_RADS
    saturated = finite & beyond.any(axis=1)
    usable = finite & ~saturated & np.isfinite(acc).all(axis=1) & np.isfinite(field).all(axis=1)
    return present, finite, saturated, usable


def test_the_compiled_checks_are_the_numpy_ones():
    rng = np.random.default_rng(4)
    count = 5000
    gyr, acc, field = (rng.normal(0, 20, (count, 3)) for _ in range(3))
    for arr in (gyr, acc, field):
        arr[rng.random((count, 3)) < 0.03] = np.nan
        arr[rng.random((count, 3)) < 0.01] = np.inf * rng.choice([-1, 1])
    gyr[rng.random(count) < 0.1] = np.nan  # whole rows absent
    gyr[rng.random((count, 3)) < 0.02] = GYRO_LIMIT_RADS * rng.choice([-1, 1])  # exactly at the limit
    out = np.empty((4, count), dtype=bool)
    _kernels.gyro_rows(gyr, acc, field, GYRO_LIMIT_RADS, *out)
    for got, want in zip(out, _plainly(gyr, acc, field)):
        np.testing.assert_array_equal(got, want)
    assert out[2].sum() > 50 and out[0].sum() < count and out[3].sum() > 1000  # every case met


def test_gravity_is_minus_down_where_fused_and_the_accelerometer_elsewhere():
    """``FusedColumns.gravity`` (a negation and a masked copy) is ``np.where(fused, -down, acc)`` to the bit, NaN rows
    included, whether none, some or all samples are fused."""
    from magnet.compass.filters import FusedColumns

    rng = np.random.default_rng(28)
    for share in (0.0, 0.3, 0.97, 1.0):
        count = 500
        columns = FusedColumns.empty(count)
        fused = rng.random(count) < share
        down = rng.normal(size=(count, 3))
        down[rng.random(count) < 0.05] = np.nan
        acc = rng.normal(size=(count, 3))
        acc[rng.random(count) < 0.05, 1] = -np.nan
        columns = FusedColumns(fused, columns.quat_wxyz, columns.heading_deg, columns.pitch_deg, columns.roll_deg,
                               down, columns.mag_disturbed, {}, 0)  # fmt: skip
        expected = np.where(fused[:, None], -down, acc)
        got = columns.gravity(acc)
        assert got.tobytes() == expected.tobytes()
        assert not np.shares_memory(got, down)
