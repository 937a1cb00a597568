"""Rotations: Euler Z-Y-X <-> matrix, axis conventions, random rotations."""

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from magnet import attitude

angles = st.tuples(st.floats(0, 359.9), st.floats(-89, 89), st.floats(-179.9, 180))


def test_yaw_90_points_body_x_east():
    r = attitude.euler_to_matrix(90.0, 0.0, 0.0)
    np.testing.assert_allclose(attitude.body_to_ned(r, np.array([1.0, 0, 0])), [0, 1, 0], atol=1e-12)


def test_pitch_up_raises_the_nose_and_roll_right_lowers_the_right_side():
    nose = attitude.body_to_ned(attitude.euler_to_matrix(0.0, 30.0, 0.0), np.array([1.0, 0, 0]))
    assert nose[2] < 0  # nose up = negative down component
    right = attitude.body_to_ned(attitude.euler_to_matrix(0.0, 0.0, 30.0), np.array([0.0, 1, 0]))
    assert right[2] > 0  # right wing down


@settings(max_examples=60, deadline=None)
@given(angles)
def test_matrix_to_euler_inverts_euler_to_matrix(ypr):
    r = attitude.euler_to_matrix(*ypr)
    back = attitude.matrix_to_euler(r)
    np.testing.assert_allclose(attitude.euler_to_matrix(*back), r, atol=1e-9)
    np.testing.assert_allclose(back[1], ypr[1], atol=1e-7)


@settings(max_examples=40, deadline=None)
@given(angles)
def test_matrices_are_proper_rotations(ypr):
    r = attitude.euler_to_matrix(*ypr)
    np.testing.assert_allclose(r @ r.T, np.eye(3), atol=1e-12)
    assert np.isclose(np.linalg.det(r), 1.0)


def test_broadcasting_and_ned_to_body_is_the_transpose():
    rng = np.random.default_rng(1)
    yaw, pitch, roll = rng.uniform(0, 360, 5), rng.uniform(-80, 80, 5), rng.uniform(-180, 180, 5)
    r = attitude.euler_to_matrix(yaw, pitch, roll)
    assert r.shape == (5, 3, 3)
    v = rng.standard_normal((5, 3))
    np.testing.assert_allclose(attitude.body_to_ned(r, attitude.ned_to_body(r, v)), v, atol=1e-12)


def test_axis_angle_and_rotation_angle_agree():
    r = attitude.axis_angle_matrix(np.array([1.0, 2.0, -0.5]), 37.0)
    assert np.isclose(attitude.rotation_angle_deg(r), 37.0)
    np.testing.assert_allclose(
        attitude.axis_angle_matrix(np.array([0, 0, 1.0]), 90.0), attitude.euler_to_matrix(90.0, 0, 0), atol=1e-12
    )


def test_random_rotations_are_uniform_enough():
    rs = attitude.random_rotations(4000, np.random.default_rng(0))
    np.testing.assert_allclose(np.einsum("nij,nkj->nik", rs, rs), np.broadcast_to(np.eye(3), rs.shape), atol=1e-12)
    # images of body x are uniform on the sphere: mean ~ 0, second moment ~ I/3
    x = rs[:, :, 0]
    assert np.abs(x.mean(axis=0)).max() < 0.05
    np.testing.assert_allclose(x.T @ x / len(x), np.eye(3) / 3, atol=0.03)
