"""The compiled kernels (magnet/_kernels.c) against the same maths written plainly here, on random inputs."""

from __future__ import annotations

import math

import numpy as np
import pytest

from magnet import _kernels

RNG = np.random.default_rng(28)


def _quats(n: int) -> np.ndarray:
    q = RNG.normal(size=(n, 4))
    return q / np.linalg.norm(q, axis=1, keepdims=True)


def _product(p: np.ndarray, q: np.ndarray) -> np.ndarray:
    """Hamilton product of (..., 4) wxyz, plainly."""
    pw, px, py, pz = np.moveaxis(p, -1, 0)
    qw, qx, qy, qz = np.moveaxis(q, -1, 0)
    return np.stack(
        [
            pw * qw - px * qx - py * qy - pz * qz,
            pw * qx + px * qw + py * qz - pz * qy,
            pw * qy - px * qz + py * qw + pz * qx,
            pw * qz + px * qy - py * qx + pz * qw,
        ],
        axis=-1,
    )


def _matrix(q: np.ndarray) -> np.ndarray:
    """Rotation matrices (n, 3, 3) of quaternions (n, 4), normalised, plainly."""
    w, x, y, z = (q / np.linalg.norm(q, axis=1, keepdims=True)).T
    return np.stack(
        [
            np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
            np.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
            np.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1),
        ],
        axis=1,
    )


def test_carry_forward_is_the_product_of_each_periods_turn():
    start, gyr, bias, period = _quats(1)[0], RNG.normal(0.0, 2.0, (50, 3)), RNG.normal(0.0, 0.1, 3), 0.01
    gyr[7] = bias  # no turn at all: the rate less the bias is zero
    out = np.empty((50, 4))
    _kernels.carry_forward(start, gyr, bias, period, out)
    q, want = start, []
    for rate in gyr - bias:
        angle = np.linalg.norm(rate) * period
        axis = rate / np.linalg.norm(rate) if angle > 0 else np.zeros(3)
        q = _product(q, np.concatenate([[math.cos(angle / 2)], math.sin(angle / 2) * axis]))
        want.append(q)
    np.testing.assert_allclose(out, want, atol=1e-13)


@pytest.mark.parametrize("conjugate, normalise", [(False, False), (True, True), (True, False)])
def test_quaternion_product_with_one_or_many_left_factors(conjugate, normalise):
    q = 1.5 * _quats(20)
    for p in (_quats(1), _quats(20)):
        out = np.empty((20, 4))
        _kernels.quaternion_product(p, q, out, conjugate, normalise)
        left = p * [1, -1, -1, -1] if conjugate else p
        want = _product(np.broadcast_to(left, q.shape), q)
        if normalise:
            want = want / np.linalg.norm(want, axis=1, keepdims=True)
        np.testing.assert_allclose(out, want, atol=1e-13)


def test_quaternion_product_writes_into_a_tables_columns_in_place():
    table = RNG.normal(size=(10, 8))
    q = table[:, 4:8].copy()
    _kernels.quaternion_product(table[:1, 0:4], table[:, 4:8], table[:, 4:8], True, True)
    want = _product(np.broadcast_to(table[:1, 0:4] * [1, -1, -1, -1], q.shape), q)
    np.testing.assert_allclose(table[:, 4:8], want / np.linalg.norm(want, axis=1, keepdims=True), atol=1e-13)


def test_into_body_is_the_transposed_rotation_of_the_enu_vector():
    q, a_ned, out = 2.0 * _quats(30), RNG.normal(size=(30, 3)), np.empty((30, 3))
    _kernels.into_body(q, a_ned, out)
    enu = a_ned[:, [1, 0, 2]] * [1, 1, -1]
    np.testing.assert_allclose(out, np.einsum("nji,nj->ni", _matrix(q), enu), atol=1e-13)


def test_piece_figures_are_the_means_of_the_field_in_the_6d_earth_frame():
    q, field, acc = _quats(12), RNG.normal(size=(12, 3)), RNG.normal(size=(12, 3))
    *up, heading, horizontal, vertical, left = _kernels.piece_figures(q, field, acc, 9.8)
    r = _matrix(q)
    earth = np.einsum("nij,nj->ni", r, field)
    phi = np.arctan2(earth[:, 0], earth[:, 1])
    np.testing.assert_allclose(up, r[-1, 2], atol=1e-14)
    assert heading == pytest.approx(math.atan2(np.mean(np.sin(phi)), np.mean(np.cos(phi))), abs=1e-13)
    assert horizontal == pytest.approx(np.mean(np.hypot(earth[:, 0], earth[:, 1])), rel=1e-13)
    assert vertical == pytest.approx(np.mean(earth[:, 2]), abs=1e-13)
    assert left == pytest.approx(np.linalg.norm(np.mean(acc - 9.8 * r[:, 2], axis=0)), rel=1e-12)
    with pytest.raises(ValueError, match="at least one sample"):
        _kernels.piece_figures(q[:0], field[:0], acc[:0], 9.8)


def test_centred_difference_is_the_slope_of_the_interpolated_fixes_where_covered():
    times = np.cumsum(RNG.uniform(0.05, 0.3, 40))
    values, h = RNG.normal(size=(40, 3)), 0.5
    t = np.concatenate([RNG.uniform(times[0] - 1, times[-1] + 1, 200), times[:3] + h, [times[-1] - h]])
    out = np.empty((len(t), 3))
    _kernels.centred_difference(times, values, t, h, out)
    ahead = np.column_stack([np.interp(t + h, times, values[:, k]) for k in range(3)])
    behind = np.column_stack([np.interp(t - h, times, values[:, k]) for k in range(3)])
    covered = (t - h >= times[0]) & (t + h <= times[-1] + 1e-9)
    np.testing.assert_allclose(out, np.where(covered[:, None], (ahead - behind) / (2 * h), 0.0), atol=1e-12)
    assert covered.sum() > 50 and (~covered).sum() > 20


def test_drift_step_is_the_kalman_filters_prediction_and_update():
    x, a = RNG.normal(size=5), RNG.normal(size=(5, 5))
    p = a @ a.T + np.eye(5)
    up, noise, dt, tau, z, r = RNG.normal(size=3), RNG.uniform(0, 1e-3, 5), 0.1, 1.8, 3.0, 1e-4
    f = np.eye(5)
    f[0, 1:4], f[4, 4] = -dt * up, math.exp(-dt / tau)
    xp, pp = f @ x, f @ p @ f.T + np.diag(noise)
    h = np.array([1.0, 0, 0, 0, 1.0])
    gain = pp @ h / (h @ pp @ h + r)
    want_x = xp + gain * math.remainder(z - h @ xp, math.tau)
    want_x[0] = math.remainder(want_x[0], math.tau)
    want_p = pp - np.outer(gain, h @ pp)
    for update, (wx, wp) in ((False, (xp, pp)), (True, (want_x, want_p))):
        got_x, got_p = x.copy(), p.copy()
        _kernels.drift_step(got_x, got_p, dt, tau, up, noise, z, r, update)
        np.testing.assert_allclose(got_x, wx, atol=1e-12)
        np.testing.assert_allclose(got_p, wp, atol=1e-12)


def test_advance_field_turns_by_rodrigues_and_keeps_rows_it_cannot_turn():
    field, gyr, lags = RNG.normal(size=(30, 3)), RNG.normal(0.0, 3.0, (30, 3)), RNG.uniform(0.0, 0.05, 30)
    lags[0], gyr[1, 2], field[2, 0], gyr[3] = 0.0, np.nan, np.inf, 0.0
    out = np.empty((30, 3))
    _kernels.advance_field(field, gyr, lags, out)
    w = -gyr * lags[:, None]
    angle = np.linalg.norm(w, axis=1)
    for i in range(4, 30):
        k = np.array([[0, -w[i, 2], w[i, 1]], [w[i, 2], 0, -w[i, 0]], [-w[i, 1], w[i, 0], 0]]) / angle[i]
        rotation = np.eye(3) + math.sin(angle[i]) * k + (1 - math.cos(angle[i])) * k @ k
        np.testing.assert_allclose(out[i], rotation @ field[i], atol=1e-13)
    np.testing.assert_array_equal(out[:4], field[:4])


def test_bad_arrays_are_refused_with_the_argument_named():
    with pytest.raises(ValueError, match="gyr"):
        _kernels.carry_forward(np.ones(4), np.ones((3, 2)), np.zeros(3), 0.01, np.empty((3, 4)))
    with pytest.raises(ValueError, match="float64"):
        _kernels.into_body(np.ones((2, 4), dtype=np.float32), np.ones((2, 3)), np.empty((2, 3)))
    with pytest.raises(ValueError, match="one row or as many"):
        _kernels.quaternion_product(np.ones((2, 4)), np.ones((3, 4)), np.empty((3, 4)))
