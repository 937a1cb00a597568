"""Frames and rotations: Euler Z-Y-X <-> matrix, quaternions, frame conversions, named alignments."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from magnet import frames
from magnet.attitude.heading import angle_difference_deg
from magnet.frames import euler_to_matrix, orientation_matrix, quaternion_to_matrix

angles = st.tuples(st.floats(0, 359.9), st.floats(-89, 89), st.floats(-179.9, 180))


def test_yaw_90_points_body_x_east():
    r = frames.euler_to_matrix(90.0, 0.0, 0.0)
    np.testing.assert_allclose(frames.body_to_ned(r, np.array([1.0, 0, 0])), [0, 1, 0], atol=1e-12)


def test_pitch_up_raises_the_nose_and_roll_right_lowers_the_right_side():
    nose = frames.body_to_ned(frames.euler_to_matrix(0.0, 30.0, 0.0), np.array([1.0, 0, 0]))
    assert nose[2] < 0  # nose up = negative down component
    right = frames.body_to_ned(frames.euler_to_matrix(0.0, 0.0, 30.0), np.array([0.0, 1, 0]))
    assert right[2] > 0  # right wing down


@settings(max_examples=30, deadline=None)
@given(angles)
def test_matrix_to_euler_inverts_euler_to_matrix(ypr):
    r = frames.euler_to_matrix(*ypr)
    back = frames.matrix_to_euler(r)
    np.testing.assert_allclose(frames.euler_to_matrix(*back), r, atol=1e-9)
    np.testing.assert_allclose(back[1], ypr[1], atol=1e-7)


@settings(max_examples=40, deadline=None)
@given(angles)
def test_matrices_are_proper_rotations(ypr):
    r = frames.euler_to_matrix(*ypr)
    np.testing.assert_allclose(r @ r.T, np.eye(3), atol=1e-12)
    assert np.isclose(np.linalg.det(r), 1.0)


def test_broadcasting_and_ned_to_body_is_the_transpose():
    rng = np.random.default_rng(1)
    yaw, pitch, roll = rng.uniform(0, 360, 5), rng.uniform(-80, 80, 5), rng.uniform(-180, 180, 5)
    r = frames.euler_to_matrix(yaw, pitch, roll)
    assert r.shape == (5, 3, 3)
    v = rng.standard_normal((5, 3))
    np.testing.assert_allclose(frames.body_to_ned(r, frames.ned_to_body(r, v)), v, atol=1e-12)


def test_axis_angle_and_rotation_angle_agree():
    r = frames.axis_angle_matrix(np.array([1.0, 2.0, -0.5]), 37.0)
    assert np.isclose(frames.rotation_angle_deg(r), 37.0)
    np.testing.assert_allclose(
        frames.axis_angle_matrix(np.array([0, 0, 1.0]), 90.0), frames.euler_to_matrix(90.0, 0, 0), atol=1e-12
    )


def test_random_rotations_are_uniform_enough():
    rs = frames.random_rotations(4000, np.random.default_rng(0))
    np.testing.assert_allclose(np.einsum("nij,nkj->nik", rs, rs), np.broadcast_to(np.eye(3), rs.shape), atol=1e-12)
    # images of body x are uniform on the sphere: mean ~ 0, second moment ~ I/3
    x = rs[:, :, 0]
    assert np.abs(x.mean(axis=0)).max() < 0.05
    np.testing.assert_allclose(x.T @ x / len(x), np.eye(3) / 3, atol=0.03)


def test_vqf_identity_is_body_x_east_level():
    heading, pitch, roll = frames.quaternion_to_euler(frames.ned_enu_attitude(np.array([1.0, 0, 0, 0])))
    assert heading == pytest.approx(90.0) and pitch == pytest.approx(0.0, abs=1e-9)
    assert roll == pytest.approx(0.0, abs=1e-9)


@pytest.mark.parametrize("angles", [(0.0, 0.0, 0.0), (123.0, 20.0, -35.0), (300.0, -50.0, 170.0)])
def test_quaternion_euler_and_frame_conversions_round_trip(angles):
    q = frames.w_positive(frames.euler_to_quaternion(*angles))
    np.testing.assert_allclose(quaternion_to_matrix(q), euler_to_matrix(*angles), atol=1e-12)
    heading, pitch, roll = frames.quaternion_to_euler(q)
    assert angle_difference_deg(heading, angles[0]) == pytest.approx(0.0, abs=1e-9)
    assert (pitch, roll) == pytest.approx(angles[1:])
    np.testing.assert_allclose(frames.ned_enu_attitude(frames.ned_enu_attitude(q)), q, atol=1e-12)
    np.testing.assert_allclose(frames.down_in_body(q), euler_to_matrix(*angles).T @ [0, 0, 1], atol=1e-12)


def test_rotate_heading_adds_declination():
    q = frames.rotate_heading(frames.w_positive(frames.euler_to_quaternion(350.0, 10.0, 5.0)), 15.0)
    heading, pitch, roll = frames.quaternion_to_euler(q)
    assert heading == pytest.approx(5.0) and (pitch, roll) == pytest.approx((10.0, 5.0))


def test_rotate_heading_of_rows_is_the_plain_product():
    """(N, 4) rows go through the compiled product (``_kernels.quaternion_product``): the very numbers of the product
    written plainly, one angle for all rows or one a row."""
    rng = np.random.default_rng(28)
    quat = rng.normal(size=(2000, 4))
    for angle in (rng.uniform(-180.0, 180.0, 2000), 12.5, np.zeros(2000)):
        half = np.radians(np.asarray(angle, dtype=float)) / 2
        turn = np.stack(np.broadcast_arrays(np.cos(half), 0.0, 0.0, np.sin(half)), axis=-1)
        plain = frames.w_positive(frames.quaternion_multiply(turn, quat))
        np.testing.assert_array_equal(frames.rotate_heading(quat, angle), plain)


@pytest.mark.parametrize(
    "name,expected",
    [
        ("none", np.eye(3)),
        ("yaw90", [[0, -1, 0], [1, 0, 0], [0, 0, 1]]),
        ("ROTATION_ROLL_180_YAW_90", [[0, 1, 0], [1, 0, 0], [0, 0, -1]]),  # ArduPilot: x=y, y=x, z=-z
        ("pitch90", [[0, 0, 1], [0, 1, 0], [-1, 0, 0]]),  # ArduPilot: x=z, z=-x
        ("0,1,0,1,0,0,0,0,-1", [[0, 1, 0], [1, 0, 0], [0, 0, -1]]),
    ],
)
def test_orientation_names(name, expected):
    assert np.allclose(orientation_matrix(name), expected)


@pytest.mark.parametrize("bad", ["roll33", "upside", [1, 0, 0, 0, 1, 0, 0, 0, -1], [1, 2, 3]])
def test_orientation_refuses_bad_input(bad):
    with pytest.raises(ValueError):
        orientation_matrix(bad)


# the maps between frames, checked against matrices written out here from the axes' definitions
NED_TO_ENU = np.array([[0.0, 1, 0], [1, 0, 0], [0, 0, -1]])
FRD_TO_FLU = np.diag([1.0, -1, -1])


def test_ned_enu_attitude_is_the_change_of_both_frames_and_its_own_inverse():
    q = frames.w_positive(np.random.default_rng(3).standard_normal((50, 4)))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    flu_enu = frames.ned_enu_attitude(q)
    # body FLU -> ENU = (NED -> ENU) (body FRD -> NED) (FLU -> FRD)
    np.testing.assert_allclose(
        quaternion_to_matrix(flu_enu), NED_TO_ENU @ quaternion_to_matrix(q) @ FRD_TO_FLU.T, atol=1e-12
    )
    np.testing.assert_allclose(frames.ned_enu_attitude(flu_enu), q, atol=1e-12)
    assert np.all(flu_enu[:, 0] >= 0)
    v = np.random.default_rng(4).standard_normal((50, 3))
    np.testing.assert_allclose(frames.ned_enu(v), v @ NED_TO_ENU.T)
    np.testing.assert_allclose(frames.frd_flu(v), v @ FRD_TO_FLU.T)
    np.testing.assert_array_equal(frames.ned_enu(frames.ned_enu(v)), v)
    np.testing.assert_array_equal(frames.frd_flu(frames.frd_flu(v)), v)


def test_hamilton_product_composes_rotations_and_the_conjugate_inverts():
    rng = np.random.default_rng(5)
    p, q = rng.standard_normal((2, 20, 4))
    p /= np.linalg.norm(p, axis=1, keepdims=True)
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    rp, rq = quaternion_to_matrix(p), quaternion_to_matrix(q)
    np.testing.assert_allclose(quaternion_to_matrix(frames.quaternion_multiply(p, q)), rp @ rq, atol=1e-12)
    np.testing.assert_allclose(quaternion_to_matrix(frames.quaternion_conjugate(p)), np.swapaxes(rp, 1, 2), atol=1e-12)


def test_rotation_vector_to_matrix_agrees_with_the_quaternion_exponential():
    w = np.vstack([np.zeros(3), np.random.default_rng(6).standard_normal((20, 3))])
    expected = quaternion_to_matrix(frames.rotation_vector_to_quaternion(w))
    np.testing.assert_allclose(frames.rotation_vector_to_matrix(w), expected, atol=1e-12)
    np.testing.assert_allclose(
        frames.rotation_vector_to_matrix(np.array([0.0, 0.0, np.pi / 2])), euler_to_matrix(90.0, 0, 0), atol=1e-12
    )


@pytest.mark.parametrize("number", sorted(frames.ROTATIONS))
def test_every_numbered_orientation_is_its_name_and_is_found_again(number):
    roll, pitch, yaw = frames.ROTATIONS[number]
    name = "_".join(f"{axis}{int(angle)}" for axis, angle in (("roll", roll), ("pitch", pitch), ("yaw", yaw)) if angle)
    np.testing.assert_allclose(orientation_matrix(name or "none"), frames.rotation_matrix(number), atol=1e-12)
    found, angle = frames.nearest_rotation(frames.rotation_matrix(number))  # 26 and 27 are 14 and 10 again
    assert angle == pytest.approx(0.0, abs=1e-6) and found <= number
    np.testing.assert_allclose(frames.rotation_matrix(found), frames.rotation_matrix(number), atol=1e-12)


def test_declination_turns_velocities_one_way_and_attitudes_the_other():
    q = frames.w_positive(frames.euler_to_quaternion(40.0, 0.0, 0.0))  # heading 40 deg from magnetic north
    true_heading = frames.quaternion_to_euler(frames.rotate_heading(q, 10.0))[0]
    assert true_heading == pytest.approx(50.0)
    nose_true_ned = frames.body_to_ned(euler_to_matrix(50.0, 0, 0), np.array([[1.0, 0, 0]]))
    nose_magnetic = frames.to_magnetic_ned(nose_true_ned, 10.0)
    np.testing.assert_allclose(
        nose_magnetic, frames.body_to_ned(euler_to_matrix(40.0, 0, 0), np.array([[1.0, 0, 0]])), atol=1e-12
    )


def test_frd_flu_of_many_rows_is_the_broadcast_product_to_the_bit():
    """(S, 3) rows flipped in one contiguous multiply (S from 64 to 2**15) are numpy's broadcast of (1, -1, -1), bit
    for bit, with NaN of both signs, zeros of both signs and infinities, contiguous or not; other shapes as before."""
    rng = np.random.default_rng(28)
    for rows in (1, 63, 64, 65, 300, 30_000, 32_768, 32_769):
        x = rng.normal(size=(rows, 3)) * 10.0 ** rng.integers(-300, 300, size=(rows, 3))
        spots = rng.random(x.shape) < 0.1
        x[spots] = rng.choice([np.nan, -np.nan, 0.0, -0.0, np.inf, -np.inf], size=int(spots.sum()))
        for v in (x, x[::-1], np.asfortranarray(x), x[:, :3]):
            flipped = frames.frd_flu(v)
            assert flipped.shape == v.shape
            assert flipped.tobytes() == (v * np.array([1.0, -1.0, -1.0])).tobytes()
    assert frames.frd_flu(np.ones(3)).tolist() == [1.0, -1.0, -1.0]
    assert frames.frd_flu(np.ones((2, 5, 3)))[1, 4].tolist() == [1.0, -1.0, -1.0]
