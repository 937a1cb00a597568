"""``compute_headings``: the accelerometer's tilt worked out only where a sample was not fused gives, on those
samples, the very bits of the whole-array maths (``magnet.attitude.heading``), NaN where ``filters.merge`` puts the
filter's attitude; the field and the flags pass through."""

from __future__ import annotations

import numpy as np

from magnet.attitude import heading as hd
from magnet.compass.tilt import compute_headings


def _plain(field: np.ndarray, acc: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    has_acc = np.isfinite(acc).all(axis=1)
    with np.errstate(invalid="ignore", divide="ignore"):
        tilted = hd.tilt_compensated_heading_deg(field, acc)
        pitch, roll = hd.pitch_roll_deg(acc)
    heading = np.where(has_acc & np.isfinite(tilted), tilted, hd.level_heading_deg(field))
    return heading, np.where(has_acc, pitch, 0.0), np.where(has_acc, roll, 0.0)


def test_tilt_only_where_not_fused_is_the_whole_arrays_maths_bit_for_bit():
    rng = np.random.default_rng(28)
    for _ in range(100):
        count = int(rng.integers(1, 300))
        field = rng.normal(0.0, 30.0, (count, 3))
        acc = rng.normal(0.0, 9.81, (count, 3))
        acc[rng.random(count) < 0.1] = np.nan  # no accelerometer
        acc[rng.random(count) < 0.05] = 0.0  # no tilt: the level heading
        flags = rng.integers(0, 64, count)
        fused = rng.random(count) < rng.choice([0.0, 0.5, 0.95, 1.0])
        out = compute_headings(field, acc, flags, fused)
        assert out.field_ut is field and out.flags is flags
        for got, want in zip((out.heading_deg, out.pitch_deg, out.roll_deg), _plain(field, acc)):
            assert got.shape == (count,)
            assert np.array_equal(got[~fused], want[~fused])  # the same bits, not merely close
            assert np.isnan(got[fused]).all()
