"""``heading.disturbance_flags`` compiled (``magnet._kernels.disturbance_bits``) against the numpy it replaced, on
random fields and accelerometers with NaN, zero and infinite rows, expectations per sample, as one value or none."""

from __future__ import annotations

import numpy as np
import pytest

from magnet.attitude import heading as hd


def _plainly(field, acc, expected_ut, expected_dip_deg, field_tol_pct=15.0, dip_tol_deg=5.0, dip_deg=None):
    b = np.asarray(field, dtype=float)
    flags = np.zeros(b.shape[:-1], dtype=np.int64)
    if expected_ut is not None:
        expected = np.asarray(expected_ut, dtype=float)
        with np.errstate(invalid="ignore"):
            disturbed = (np.abs(hd.row_norm(b) - expected) > expected * field_tol_pct / 100.0) & (expected > 0)
        flags |= np.where(disturbed, int(hd.HeadingFlag.FIELD_DISTURBED), 0)
    if acc is None:
        return flags | int(hd.HeadingFlag.NO_TILT)
    f = np.broadcast_to(np.asarray(acc, dtype=float), b.shape)
    norm = hd.row_norm(f)
    no_tilt = ~(np.isfinite(norm) & (norm > 1e-12))
    flags |= np.where(no_tilt, int(hd.HeadingFlag.NO_TILT), 0)
    if expected_dip_deg is not None:
        dip = hd.dip_angle_deg(b, f) if dip_deg is None else dip_deg
        with np.errstate(invalid="ignore"):
            dip_off = np.abs(dip - np.asarray(expected_dip_deg, dtype=float)) > dip_tol_deg
        flags |= np.where(dip_off & ~no_tilt, int(hd.HeadingFlag.DIP_DISTURBED), 0)
    return flags


@pytest.mark.parametrize("case", range(6))
def test_the_compiled_flags_are_the_numpy_ones(case):
    rng = np.random.default_rng(case)
    count = 3000
    field = rng.normal(0, 30, (count, 3))
    acc = rng.normal(0, 6, (count, 3)) + [0, 0, -9.8]
    acc[rng.random(count) < 0.05] = 0.0
    acc[rng.random((count, 3)) < 0.03] = np.nan
    field[rng.random((count, 3)) < 0.02] = np.inf
    expected = rng.uniform(-5, 70, count)
    expected[rng.random(count) < 0.1] = np.nan
    dip_expected = rng.uniform(-90, 90, count)
    args = [
        (field, acc, expected, dip_expected),
        (field, None, expected, dip_expected),
        (field, acc, 48.0, 60.0),
        (field, acc, None, None),
        (field, acc[0], expected, None),
        (field[0], acc[0], 50.0, 65.0),
    ][case]
    got = hd.disturbance_flags(*args, field_tol_pct=12.0, dip_tol_deg=4.0)
    want = _plainly(*args, field_tol_pct=12.0, dip_tol_deg=4.0)
    np.testing.assert_array_equal(got, want)
    dip = hd.dip_angle_deg(field, acc)
    np.testing.assert_array_equal(
        hd.disturbance_flags(field, acc, expected, dip_expected, dip_deg=dip),
        _plainly(field, acc, expected, dip_expected, dip_deg=dip),
    )
