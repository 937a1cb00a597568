"""Heading maths: cardinal points, tilt compensation, pitch/roll signs, circular smoothing, dip and flags."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from magnet.attitude import heading as hd
from magnet.frames import euler_to_matrix, ned_to_body

G = 9.80665
B_NED = np.array([19.2, 2.9, 47.2])  # Kyiv-like field, uT (north, east, down)
MAG_NORTH_DEG = np.degrees(np.arctan2(B_NED[1], B_NED[0]))


def body(yaw, pitch, roll, vector=B_NED):
    return ned_to_body(euler_to_matrix(yaw, pitch, roll), vector)


def acc_body(yaw, pitch, roll):
    return body(yaw, pitch, roll, np.array([0.0, 0.0, -G]))


@pytest.mark.parametrize("magnetic, expected", [(0, 0), (90, 90), (180, 180), (270, 270), (45, 45), (315, 315)])
def test_level_heading_at_cardinal_points(magnetic, expected):
    field = body(magnetic + MAG_NORTH_DEG, 0, 0)
    assert hd.level_heading_deg(field) == pytest.approx(expected, abs=1e-9)
    assert hd.tilt_compensated_heading_deg(field, acc_body(magnetic + MAG_NORTH_DEG, 0, 0)) == pytest.approx(
        expected, abs=1e-9
    )


def test_level_heading_axes_by_hand():
    # facing east (x east, y south): the field's north part lies on -y
    assert hd.level_heading_deg(np.array([0.0, -20.0, 40.0])) == pytest.approx(90.0)
    assert hd.level_heading_deg(np.array([0.0, 20.0, 40.0])) == pytest.approx(270.0)
    assert hd.level_heading_deg(np.array([-20.0, 0.0, 40.0])) == pytest.approx(180.0)
    out = hd.level_heading_deg(np.array([[20.0, -1e-9, 0], [20.0, 1e-9, 0]]))
    assert np.all((out >= 0) & (out < 360))


@pytest.mark.parametrize("magnetic", [0, 90, 180, 270])
@pytest.mark.parametrize("pitch, roll", [(30, 0), (-30, 0), (0, 40), (0, -40), (25, -35), (60, 120)])
def test_tilt_compensated_cardinal_points(magnetic, pitch, roll):
    yaw = magnetic + MAG_NORTH_DEG
    got = hd.tilt_compensated_heading_deg(body(yaw, pitch, roll), acc_body(yaw, pitch, roll))
    assert abs(hd.angle_difference_deg(got, magnetic)) < 1e-9
    # the level formula is wrong under tilt: the compensation matters
    if pitch and magnetic in (90, 270):
        assert abs(hd.angle_difference_deg(hd.level_heading_deg(body(yaw, pitch, roll)), magnetic)) > 5


@settings(max_examples=40, deadline=None)
@given(st.floats(0, 360), st.floats(-85, 85), st.floats(-180, 180), st.floats(0.2, 5.0))
def test_tilt_compensation_recovers_any_attitude(yaw, pitch, roll, scale):
    field, acc = body(yaw, pitch, roll), acc_body(yaw, pitch, roll) * scale
    got = hd.tilt_compensated_heading_deg(field * scale, acc)
    assert abs(hd.angle_difference_deg(got, yaw - MAG_NORTH_DEG)) < 1e-6
    p, r = hd.pitch_roll_deg(acc)
    assert p == pytest.approx(pitch, abs=1e-7)
    assert abs(hd.angle_difference_deg(r, roll)) < 1e-6
    assert hd.dip_angle_deg(field, acc) == pytest.approx(np.degrees(np.arctan2(B_NED[2], np.hypot(*B_NED[:2]))))


def test_pitch_and_roll_sign_conventions():
    assert hd.pitch_roll_deg(np.array([0.0, 0.0, -G])) == pytest.approx((0.0, 0.0))
    # nose up: the accelerometer's x axis points partly up, so it reads +g sin(pitch)
    pitch, roll = hd.pitch_roll_deg(np.array([G * np.sin(np.radians(20)), 0.0, -G * np.cos(np.radians(20))]))
    assert pitch == pytest.approx(20.0) and roll == pytest.approx(0.0)
    # right side down: y points partly down and reads -g sin(roll)
    pitch, roll = hd.pitch_roll_deg(np.array([0.0, -G * np.sin(np.radians(30)), -G * np.cos(np.radians(30))]))
    assert roll == pytest.approx(30.0) and pitch == pytest.approx(0.0)
    assert hd.pitch_roll_deg(np.array([0.0, 0.0, G]))[1] == pytest.approx(180.0)  # upside down: 180, not -180


def test_vectorized_shapes():
    rng = np.random.default_rng(0)
    field, acc = rng.standard_normal((7, 3)), rng.standard_normal((7, 3))
    assert hd.tilt_compensated_heading_deg(field, acc).shape == (7,)
    assert hd.level_heading_deg(field).shape == (7,)
    assert hd.dip_angle_deg(field, acc).shape == (7,)
    assert all(x.shape == (7,) for x in hd.pitch_roll_deg(acc))
    assert hd.disturbance_flags(field, acc, 50.0, 60.0).shape == (7,)


def test_zero_acceleration_gives_nan_not_a_wrong_heading():
    assert np.isnan(hd.tilt_compensated_heading_deg(np.array([20.0, 0, 40]), np.zeros(3)))


def test_true_heading_adds_declination_and_wraps():
    assert hd.true_heading_deg(355.0, 8.5) == pytest.approx(3.5)
    assert hd.true_heading_deg(3.0, -5.0) == pytest.approx(358.0)
    np.testing.assert_allclose(hd.true_heading_deg(np.array([0.0, 180.0]), 10.0), [10.0, 190.0])


def test_wrap_deg_gives_np_mods_very_bits():
    """wrap_deg's fast path (angles in [-360, 360): adds 360 to the negative ones) against np.mod, the plain maths,
    bit for bit, signed zeros and the rounding up to 360 included; other angles take np.mod itself."""
    rng = np.random.default_rng(4)
    edges = [-0.0, 0.0, -360.0, -1e-17, -1e-300, 359.99999999999994, -180.0, 180.0, -359.9999999999999]
    for angles in (np.concatenate([rng.uniform(-360, 360, 5000), edges]), np.array([720.5, -1e6, np.nan, 10.0])):
        plain = np.mod(angles, 360.0)
        plain = np.where(plain >= 360.0, 0.0, plain)
        np.testing.assert_array_equal(hd.wrap_deg(angles).view(np.int64), plain.view(np.int64))
    assert hd.wrap_deg(-1e-17) == 0.0 and hd.wrap_deg(np.zeros(0)).shape == (0,)


def test_smoothing_across_north_never_averages_to_south():
    headings = np.array([359.0, 1.0, 359.0, 1.0, 359.0, 1.0])
    smoothed = hd.smooth_heading_deg(headings, 2)
    assert np.all(np.abs(hd.angle_difference_deg(smoothed, 0.0)) <= 1.0 + 1e-9)
    assert np.all(np.abs(hd.angle_difference_deg(smoothed[1:], 0.0)) < 1e-9)


def test_smoothing_is_a_trailing_circular_mean():
    rng = np.random.default_rng(3)
    headings = rng.uniform(0, 360, 50)
    window = 5
    smoothed = hd.smooth_heading_deg(headings, window)
    for i in (0, 3, 4, 20, 49):
        part = np.radians(headings[max(0, i - window + 1) : i + 1])
        expected = np.degrees(np.arctan2(np.sin(part).sum(), np.cos(part).sum())) % 360
        assert abs(hd.angle_difference_deg(smoothed[i], expected)) < 1e-9
    np.testing.assert_allclose(hd.smooth_heading_deg(headings, 1), headings, atol=1e-9)


@settings(max_examples=40, deadline=None)
@given(st.floats(0, 360), st.floats(0, 20), st.integers(1, 12))
def test_smoothing_a_steady_jittered_heading_stays_near_it(center, jitter, window):
    offsets = np.tile([-jitter, jitter], 10)
    smoothed = hd.smooth_heading_deg(np.mod(center + offsets, 360.0), window)
    assert np.all(np.abs(hd.angle_difference_deg(smoothed, center)) <= jitter + 1e-6)


@pytest.mark.parametrize("window", [0, -1, 2.5, True])
def test_bad_smoothing_window_is_refused(window):
    with pytest.raises(ValueError, match="window"):
        hd.smooth_heading_deg(np.zeros(3), window)


def test_disturbance_flags():
    field, acc = body(30.0, 10.0, -5.0), acc_body(30.0, 10.0, -5.0)
    dip = hd.dip_angle_deg(field, acc)
    total = np.linalg.norm(B_NED)
    assert hd.disturbance_flags(field, acc, total, dip) == 0
    assert hd.disturbance_flags(field * 1.3, acc, total, dip) == hd.HeadingFlag.FIELD_DISTURBED
    bent = body(30.0, 10.0, -5.0, np.array([40.0, 0.0, 30.0])) * total / 50.0  # same |B|, dip 37 deg
    assert hd.disturbance_flags(bent, acc, total, dip) == hd.HeadingFlag.DIP_DISTURBED
    assert hd.disturbance_flags(field, None, total, dip) == hd.HeadingFlag.NO_TILT
    assert hd.disturbance_flags(field, np.zeros(3), total, dip) == hd.HeadingFlag.NO_TILT
    assert hd.disturbance_flags(field * 3, acc, None, None) == 0  # nothing expected, nothing flagged


def test_heading_uncertainty_grows_as_the_horizontal_field_shrinks():
    acc = np.array([0.0, 0.0, -G])
    strong = hd.heading_uncertainty_deg(np.array([20.0, 0.0, 45.0]), acc, 0.35)
    weak = hd.heading_uncertainty_deg(np.array([2.0, 0.0, 45.0]), acc, 0.35)
    assert strong == pytest.approx(np.degrees(np.arctan(0.35 / 20.0)))
    assert weak > 5 * strong
    assert hd.heading_uncertainty_deg(np.array([0.0, 0.0, 45.0]), acc, 0.35) == 180.0


def test_the_compiled_tilt_heading_and_dip_are_the_plain_maths():
    """``tilt_compensated_heading_deg`` and ``dip_angle_deg`` (compiled: ``magnet._kernels.tilt_heading``) against
    the cross products written plainly in numpy, on random vectors with zero, NaN and broadcast ones."""
    rng = np.random.default_rng(9)
    field, acc = rng.normal(0, 40, (2000, 3)), rng.normal(0, 9, (2000, 3))
    acc[::50], acc[1::50], field[2::50] = 0.0, np.nan, 0.0
    with np.errstate(divide="ignore", invalid="ignore"):
        norm = np.linalg.norm(acc, axis=1)
        d = acc * np.where(norm > 1e-12, -1.0 / norm, np.nan)[:, None]
        east = np.cross(d, field)
        plain = np.degrees(np.arctan2(east[:, 0], np.cross(east, d)[:, 0])) % 360.0
        plain_dip = np.degrees(np.arcsin(np.clip(np.sum(field * d, axis=1) / np.linalg.norm(field, axis=1), -1, 1)))
    np.testing.assert_allclose(hd.tilt_compensated_heading_deg(field, acc), plain, atol=1e-9)
    np.testing.assert_allclose(hd.dip_angle_deg(field, acc), plain_dip, atol=1e-9)
    assert np.array_equal(np.isnan(hd.tilt_compensated_heading_deg(field, acc)), np.isnan(plain))
    one = hd.tilt_compensated_heading_deg(field[:5], acc[7])  # one accelerometer reading for every field
    np.testing.assert_allclose(one, [hd.tilt_compensated_heading_deg(f, acc[7]) for f in field[:5]])
