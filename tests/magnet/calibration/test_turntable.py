"""Turntable calibration (seed 000): the closed form reproduces the seed's Table 2 from its Table 1."""

from __future__ import annotations

import numpy as np
import pytest

from magnet.calibration import FitError
from magnet.calibration.turntable import closed_form, field_in_sensor, fit_turntable, least_squares

BH, BV = 18964.0, -46962.0  # gammas (nT)

# Seed 000, Table 1 (docs/design.md, "The turntable closed form"): heading K (deg); Ux a, Ux b, Uy a, Uy b, Uz a,
# Uz b (sensor codes, averaged per angle)
TABLE_1 = np.array(
    [
        [0, 240.3558, 232.6558, -258.4923, 256.7519, -282.8714, 114.7131],
        [30, 209.1716, 199.1959, -135.2888, 266.9017, -284.4551, 219.0599],
        [60, 125.5631, 113.8107, -44.8091, 275.2361, -285.0419, 295.5739],
        [90, 11.7449, -0.6559, -11.2143, 279.9059, -283.6456, 325.0541],
        [120, -101.7102, -113.4541, -43.7399, 277.8303, -280.5519, 298.9297],
        [150, -183.9562, -194.1136, -132.7759, 271.8628, -277.0101, 225.2665],
        [180, -213.7425, -222.0211, -254.4305, 262.3875, -272.8729, 122.2481],
        [210, -182.9617, -189.2329, -376.6771, 251.5309, -270.6257, 17.9088],
        [240, -100.0683, -104.4479, -466.2854, 243.4397, -269.3543, -60.2063],
        [270, 13.9952, 10.4205, -499.7591, 238.7882, -270.5577, -90.3142],
        [300, 127.5779, 123.8926, -468.2123, 240.2207, -273.7365, -64.6301],
        [330, 210.3789, 205.7122, -379.3324, 246.4799, -277.4887, 10.9891],
        [360, 240.1131, 233.0065, -257.2397, 256.5758, -281.6103, 114.9137],
    ]
)
ANGLES = TABLE_1[:, 0].astype(int)
MOUNT_A = TABLE_1[:, [1, 3, 5]]
MOUNT_B = TABLE_1[:, [2, 4, 6]]

# Seed 000, Table 2, as printed: K row by row, then u0
TABLE_2_K = np.array([[0.012, -5.9333e-5, -1.1079e-4], [-1.0709e-4, 0.0129, -0.0019], [-2.6362e-4, -3.4507e-4, 0.0088]])
TABLE_2_U0 = np.array([8.1037, -345.3406, 134.6858])
# half a unit of the last printed digit of each figure above
TABLE_2_K_HALF_ULP = 0.5 * np.array([[1e-3, 1e-9, 1e-8], [1e-8, 1e-4, 1e-4], [1e-9, 1e-9, 1e-4]])
TABLE_2_U0_HALF_ULP = 0.5 * np.array([1e-4, 1e-4, 1e-4])
TABLE_1_HALF_ULP = 0.5e-4  # Table 1 is printed to 4 decimals


def _readings(table: np.ndarray) -> dict[int, np.ndarray]:
    return {int(a): row for a, row in zip(ANGLES[:-1], table[:-1])}


def _propagated_rounding_bound() -> tuple[np.ndarray, np.ndarray]:
    """Worst-case change of K and u0 when every Table 1 reading moves by up to half its last digit.

    The closed form is linear in the readings, so the bound is the sum over readings of |d(output)/d(reading)| times
    0.5e-4; the derivatives are exact finite differences of a unit step.
    """
    base_k, base_u0 = closed_form(_readings(MOUNT_A), _readings(MOUNT_B), BH, BV)
    bound_k, bound_u0 = np.zeros((3, 3)), np.zeros(3)
    for table_index in range(2):
        for row in range(len(ANGLES) - 1):
            for axis in range(3):
                tables = [MOUNT_A.copy(), MOUNT_B.copy()]
                tables[table_index][row, axis] += 1.0
                k, u0 = closed_form(_readings(tables[0]), _readings(tables[1]), BH, BV)
                bound_k += np.abs(k - base_k) * TABLE_1_HALF_ULP
                bound_u0 += np.abs(u0 - base_u0) * TABLE_1_HALF_ULP
    return bound_k, bound_u0


def test_closed_form_reproduces_table_2():
    k, u0 = closed_form(_readings(MOUNT_A), _readings(MOUNT_B), BH, BV)
    # Table 2 was computed from unrounded readings and then printed rounded; Table 1 as printed is rounded too.
    # So agreement is expected within half a unit of Table 2's last digit plus what Table 1's rounding can move.
    bound_k, bound_u0 = _propagated_rounding_bound()
    assert np.all(np.abs(k - TABLE_2_K) <= TABLE_2_K_HALF_ULP + bound_k), (k, TABLE_2_K)
    assert np.all(np.abs(u0 - TABLE_2_U0) <= TABLE_2_U0_HALF_ULP + bound_u0), (u0, TABLE_2_U0)
    # the bound is tight enough to mean something: it is far below the figures themselves
    assert np.all(bound_k < 1e-3 * np.abs(TABLE_2_K)) and np.all(bound_u0 < 1e-3)


def _samples(include_360: bool = False) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    rows = slice(None) if include_360 else slice(0, -1)
    mag = np.vstack([MOUNT_A[rows], MOUNT_B[rows]])
    mounting = np.array(["a"] * len(ANGLES[rows]) + ["b"] * len(ANGLES[rows]))
    heading = np.concatenate([ANGLES[rows], ANGLES[rows]]).astype(float)
    return mag, mounting, heading


def test_fit_turntable_closed_matches_closed_form_and_table_3():
    mag, mounting, heading = _samples()
    cal = fit_turntable(mag, mounting, heading, BH, BV, field_unit="nt")
    k, u0 = closed_form(_readings(MOUNT_A), _readings(MOUNT_B), BH, BV)
    assert np.allclose(cal.matrix, np.linalg.inv(k)) and np.allclose(cal.offset, u0)
    assert cal.method == "turntable" and cal.output_unit == "nt"
    # Table 3 (calibrated mounting a): |T| near sqrt(Bh^2 + Bv^2) = 50,646 nT, Tz near Bv, Tx near Bh cos K
    t = cal.apply(MOUNT_A)
    assert np.all(np.abs(np.linalg.norm(t, axis=1) / np.hypot(BH, BV) - 1) < 0.03)
    assert np.all(np.abs(t[:, 2] - BV) < 0.03 * abs(BV))
    assert np.allclose(t[:, 0], BH * np.cos(np.radians(ANGLES)), atol=0.03 * BH)
    assert t[0] == pytest.approx([BH, 0.0, BV], abs=1e-6)  # exact at the angles the closed form used


def test_lsq_variant_on_the_seed_data():
    mag, mounting, heading = _samples()
    closed = fit_turntable(mag, mounting, heading, BH, BV, field_unit="nt")
    lsq = fit_turntable(mag, mounting, heading, BH, BV, variant="lsq", field_unit="nt")
    assert lsq.method == "turntable-lsq"
    # the least-squares solution is optimal over all 24 readings, so it cannot fit them worse than the closed form
    assert lsq.quality["vector_rms"] <= closed.quality["vector_rms"]
    # and lands near it, though not very near: the seed's readings do not fit one linear model across both
    # mountings (even the best 12-parameter fit leaves ~19 codes RMS on y and ~14 on z, against ~0.4 within mounting
    # a alone), so the two variants weigh the inconsistency differently. x, seen alike in both mountings, agrees to
    # 0.2 %; the y and z gains differ by up to 13 %. On consistent data they agree closely (next test).
    k_closed, k_lsq = np.linalg.inv(closed.matrix), np.linalg.inv(lsq.matrix)
    assert k_lsq[0, 0] == pytest.approx(k_closed[0, 0], rel=2e-3)
    assert np.allclose(np.diag(k_lsq), np.diag(k_closed), rtol=0.15)
    assert np.linalg.norm(k_lsq - k_closed) < 0.15 * np.linalg.norm(k_closed)


def test_lsq_and_closed_form_agree_on_consistent_data():
    rng = np.random.default_rng(0)
    k_true = np.diag([0.012, 0.013, 0.009]) + rng.normal(scale=3e-4, size=(3, 3))
    u0_true = np.array([8.0, -345.0, 135.0])
    angles = np.repeat(np.arange(0, 360, 30), 20).astype(float)
    mag, mounting = [], []
    for name in ("a", "b"):
        field = field_in_sensor(name, angles, BH, BV)
        mag.append(field @ k_true.T + u0_true + rng.normal(scale=0.3, size=field.shape))
        mounting += [name] * len(angles)
    mag = np.vstack(mag)
    heading = np.concatenate([angles, angles])
    fitted = {}
    for variant in ("closed", "lsq"):
        cal = fit_turntable(mag, np.array(mounting), heading, BH, BV, variant=variant, field_unit="nt")
        fitted[variant] = np.linalg.inv(cal.matrix)
        # 0.3-code noise against gains of ~0.012 code/nT: K to 0.1 % of a gain, u0 to a fraction of a code
        assert np.allclose(fitted[variant], k_true, atol=1e-3 * 0.013), variant
        assert np.allclose(cal.offset, u0_true, atol=0.3), variant
        assert cal.accepted, cal.reason
    assert np.allclose(fitted["closed"], fitted["lsq"], atol=1e-3 * 0.013)


def test_360_is_a_closing_check_not_averaged_into_0_and_missing_angles_are_named():
    mag, mounting, heading = _samples(include_360=True)
    cal = fit_turntable(mag, mounting, heading, BH, BV, field_unit="nt")
    assert cal.sample_count == 26
    # seed 000's closed form uses the 0 deg readings; the 360 deg row only shows that the turn closed
    assert cal.offset == pytest.approx(fit_turntable(*_samples(), BH, BV, field_unit="nt").offset)
    only_360 = ~(heading == 0)
    from_360 = fit_turntable(mag[only_360], mounting[only_360], heading[only_360], BH, BV, field_unit="nt")
    assert from_360.offset != pytest.approx(cal.offset)  # with no 0 deg reading, 360 stands in for it
    keep = ~((mounting == "a") & (heading == 90))
    with pytest.raises(FitError, match="mounting a at 90 deg"):
        fit_turntable(mag[keep], mounting[keep], heading[keep], BH, BV, field_unit="nt")
    lsq = fit_turntable(mag[keep], mounting[keep], heading[keep], BH, BV, variant="lsq", field_unit="nt")
    assert lsq.sample_count == int(keep.sum())


def test_bad_turntable_input():
    mag, mounting, heading = _samples()
    with pytest.raises(FitError, match="both mountings"):
        least_squares(mag[mounting == "a"], field_in_sensor("a", heading[mounting == "a"], BH, BV))
    with pytest.raises(FitError, match="unknown mounting"):
        fit_turntable(mag, np.where(mounting == "a", "c", "b"), heading, BH, BV, field_unit="nt")
    with pytest.raises(FitError, match="one entry per sample"):
        fit_turntable(mag, mounting[:-1], heading, BH, BV, field_unit="nt")
    with pytest.raises(FitError, match="variant"):
        fit_turntable(mag, mounting, heading, BH, BV, variant="magic")
