"""The compiled kernels (magnet/_kernels.c) against the same maths written plainly here, on random inputs."""

from __future__ import annotations

import math

import numpy as np
import pytest

from magnet import _kernels
from magnet.attitude.field_watch import FieldWatch, WatchSettings

RNG = np.random.default_rng(28)


def _quats(n: int) -> np.ndarray:
    q = RNG.normal(size=(n, 4))
    return q / np.linalg.norm(q, axis=1, keepdims=True)


def _product(p: np.ndarray, q: np.ndarray) -> np.ndarray:
    """Hamilton product of (..., 4) wxyz, plainly."""
    pw, px, py, pz = (p[..., k] for k in range(4))
    qw, qx, qy, qz = (q[..., k] for k in range(4))
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


def test_vqf_attitudes_are_the_frames_conversions_of_the_finite_rows():
    n = 400
    raw = _quats(n) * RNG.uniform(0.5, 2.0, (n, 1))
    raw[::7] = np.nan  # not fused
    raw[3, 2] = np.inf
    fused, rotation = np.empty(n, dtype=bool), np.empty((n, 3, 3))
    quat, down, angles = np.empty((n, 4)), np.empty((n, 3)), np.empty((3, n))
    _kernels.vqf_attitudes(raw, fused, quat, rotation.reshape(n, 9), down, *angles)
    want_fused = np.isfinite(raw).all(axis=1)
    np.testing.assert_array_equal(fused, want_fused)
    # the plain maths: q_NED_ENU q q_FRD_FLU with w >= 0, its matrix, Z-Y-X Euler angles in degrees
    h = math.sqrt(0.5)
    plain = _product(_product(np.array([0.0, h, h, 0.0]), raw[fused]), np.array([0.0, 1.0, 0.0, 0.0]))
    plain *= np.where(plain[:, :1] < 0, -1.0, 1.0)
    m = _matrix(plain)
    np.testing.assert_allclose(quat[fused], plain, atol=1e-15)
    np.testing.assert_allclose(rotation[fused], m, atol=1e-14)
    np.testing.assert_array_equal(down[fused], rotation[fused][:, 2, :])
    heading = np.degrees(np.arctan2(m[:, 1, 0], m[:, 0, 0])) % 360.0
    np.testing.assert_allclose(angles[0][fused], heading, atol=1e-9)
    np.testing.assert_allclose(angles[1][fused], np.degrees(np.arcsin(np.clip(-m[:, 2, 0], -1, 1))), atol=1e-9)
    np.testing.assert_allclose(angles[2][fused], np.degrees(np.arctan2(m[:, 2, 1], m[:, 2, 2])), atol=1e-9)
    assert ((angles[0][fused] >= 0) & (angles[0][fused] < 360)).all()
    assert np.isnan(quat[~fused]).all() and np.isnan(down[~fused]).all() and np.isnan(angles[:, ~fused]).all()
    np.testing.assert_array_equal(rotation[~fused], np.broadcast_to(np.eye(3), (int((~fused).sum()), 3, 3)))
    # without the matrices (the compass without its sigmas): the same attitudes and angles
    again = [np.empty(n, dtype=bool), np.empty((n, 4)), np.empty((n, 3)), np.empty((3, n))]
    _kernels.vqf_attitudes(raw, again[0], again[1], None, again[2], *again[3])
    for got, want in zip(again, (fused, quat, down, angles)):
        np.testing.assert_array_equal(got, want)


def test_turn_about_down_is_the_product_with_the_turn_then_w_positive():
    n = 300
    quat, angle, out = _quats(n), RNG.uniform(-400.0, 400.0, n), np.empty((n, 4))
    quat[::9] = np.nan
    _kernels.turn_about_down(quat, angle, out)
    half = np.radians(angle) / 2
    plain = _product(np.stack([np.cos(half), 0 * half, 0 * half, np.sin(half)], -1), quat)
    plain *= np.where(plain[:, :1] < 0, -1.0, 1.0)
    np.testing.assert_allclose(out, plain, atol=1e-15)
    assert np.array_equal(np.isnan(out), np.isnan(plain))


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


def _integrated(gyr: np.ndarray, period_s: float, start: np.ndarray) -> np.ndarray:
    """q_k = q_{k-1} exp(w_k dt), one product at a time, each normalised: in Python floats (numpy's calls on one
    quaternion at a time cost ten times the maths)."""
    out, (w, x, y, z) = [], start.tolist()
    for rx, ry, rz in (gyr * period_s).tolist():
        angle = math.sqrt(rx * rx + ry * ry + rz * rz)
        s = math.sin(angle / 2) / angle if angle > 1e-12 else 0.0
        a, b, c, d = math.cos(angle / 2), s * rx, s * ry, s * rz
        w, x, y, z = (
            w * a - x * b - y * c - z * d,
            w * b + x * a + y * d - z * c,
            w * c - x * d + y * a + z * b,
            w * d + x * c - y * b + z * a,
        )
        norm = math.sqrt(w * w + x * x + y * y + z * z)
        w, x, y, z = w / norm, x / norm, y / norm, z / norm
        out.append((w, x, y, z))
    return np.array(out).reshape(-1, 4)


_SETTINGS = WatchSettings()


class _PlainWatch:
    """FieldWatch as it was written in numpy before it was compiled: the maths, plainly."""

    BLOCK_S = 0.5

    def __init__(self, period_s: float, settings: WatchSettings = _SETTINGS) -> None:
        self.period_s, self.settings = float(period_s), settings
        self.widths = [max(1, round(window / self.period_s)) for window, _ in settings.steps]
        self.smooth = max(1, round(settings.smooth_s / self.period_s))
        self.hold = round(settings.hold_s / self.period_s)
        self.block = max(1, round(self.BLOCK_S / self.period_s))
        self.reset()

    def reset(self) -> None:
        """Forget everything (the filter restarted)."""
        self.quat = np.array([1.0, 0.0, 0.0, 0.0])
        self.tail = np.zeros((0, 3))
        self.tail_turn = np.zeros(0)
        self.turned = 0.0
        self.samples = 0
        self.reference_ut = 0.0
        self.levels = np.zeros(len(self.widths) + 1)  # usual step statistics, then usual | |B| - reference |
        self.hold_left = 0
        self.flagged_run = 0  # flagged samples in a row up to the last one
        self.pending: list[tuple[np.ndarray, np.ndarray]] = []  # this block's statistics and calm norms so far

    def _statistics(self, field: np.ndarray, gyr: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """((n, steps + 1), (n, steps)): each window's change of the smoothed field in the integrated frame (NaN
        where the history is too short), then | |B| - reference |; and each window's turn (rad, + turn_floor_rad)."""
        quat = _integrated(gyr, self.period_s, self.quat)
        self.quat = quat[-1]
        world = np.concatenate([self.tail, np.einsum("nij,nj->ni", _matrix(quat), field)])
        travelled = self.turned + np.cumsum(_norm(gyr)) * self.period_s  # rad turned since the start
        self.turned = float(travelled[-1])
        turns = np.concatenate([self.tail_turn, travelled])
        sums = np.concatenate([np.zeros((1, 3)), np.cumsum(world, axis=0)])
        index = np.arange(len(world))
        low = np.maximum(index + 1 - self.smooth, 0)
        smooth = (sums[index + 1] - sums[low]) / (index + 1 - low)[:, None]
        new = index[len(self.tail) :]
        out = np.full((len(field), len(self.widths) + 1), np.nan)
        turned = np.ones((len(field), len(self.widths)))
        for j, width in enumerate(self.widths):
            valid = new - width >= self.smooth - 1
            now, then = new[valid], new[valid] - width
            out[valid, j] = _norm(smooth[now] - smooth[then])
            turned[valid, j] = turns[now] - turns[then] + self.settings.turn_floor_rad  # the path, not the net turn
        out[:, -1] = np.abs(_norm(field) - self.reference_ut)
        keep = max(self.widths) + self.smooth
        self.tail, self.tail_turn = world[-keep:], turns[-keep:]
        return out, turned

    def _held(self, raw: np.ndarray) -> np.ndarray:
        """Flags held ``hold`` samples after each, across batches."""
        n = len(raw)
        index = np.arange(n)
        last = np.maximum.accumulate(np.where(raw, index, -(self.hold + 1) - n))
        flagged = raw | (index - last <= self.hold) | (index < self.hold_left)
        self.hold_left = max(self.hold - (n - 1 - int(last[-1])), self.hold_left - n, 0)
        return flagged

    def _learn(self) -> None:
        """At a block's end: move the reference |B| towards its undisturbed samples and the usual levels towards
        the 90th percentile of all its samples' statistics (a disturbance of a few seconds moves them little, a
        device that turns faster than before a lot); a field flagged for longer than ``max_reject_s`` is accepted as
        the new normal and learnt again."""
        if self.flagged_run * self.period_s > self.settings.max_reject_s:
            self.reference_ut, self.levels[:], self.hold_left, self.flagged_run = 0.0, 0.0, 0, 0
        statistics = np.concatenate([part[0] for part in self.pending]) if self.pending else np.zeros((0, 1))
        norm = np.concatenate([part[1] for part in self.pending]) if self.pending else np.zeros(0)
        self.pending = []
        if len(statistics) == 0:
            return
        seconds = len(statistics) * self.period_s
        seen_s = self.samples * self.period_s
        alpha = max(-np.expm1(-seconds / self.settings.level_tau_s), min(1.0, seconds / max(seen_s, seconds)))
        if self.reference_ut == 0.0 and norm.size:
            self.reference_ut, alpha = float(np.median(norm)), 1.0
        if norm.size:
            self.reference_ut += alpha * (float(norm.mean()) - self.reference_ut)
        for j in range(statistics.shape[1]):
            values = statistics[:, j]
            values = values[np.isfinite(values)]
            if values.size:
                self.levels[j] += alpha * (float(np.percentile(values, 90)) - self.levels[j])

    def _judge(self, field: np.ndarray, gyr: np.ndarray) -> np.ndarray:
        """Flags of samples within one block (references as at the block's start)."""
        settings = self.settings
        statistics, turned = self._statistics(field, gyr)
        floors = [floor for _, floor in settings.steps] + [settings.field_tol_pct / 100.0 * self.reference_ut]
        scale = np.column_stack([turned, np.ones(len(field))])  # steps per radian turned; |B| as it is
        limits = np.maximum(np.asarray(floors), settings.relative * self.levels * scale)
        ready = self.samples * self.period_s >= settings.learn_s and self.reference_ut > 0.0
        with np.errstate(invalid="ignore"):
            flagged = self._held((statistics > limits).any(axis=1) & ready)
        calm = ~flagged
        self.pending.append((statistics / scale, _norm(field[calm])))
        trailing = len(flagged) if flagged.all() else int(np.argmin(flagged[::-1]))
        self.flagged_run = self.flagged_run + trailing if flagged.all() else trailing
        return flagged

    def update(self, field: np.ndarray, gyr_rads: np.ndarray) -> np.ndarray:
        """(n,) bool: the samples of this batch (field (n, 3) corrected, gyr_rads (n, 3), the same body frame) that
        are disturbed."""
        out = np.zeros(len(field), dtype=bool)
        start = 0
        while start < len(field):
            stop = min(len(field), start + self.block - self.samples % self.block)
            out[start:stop] = self._judge(field[start:stop], gyr_rads[start:stop])
            self.samples += stop - start
            if self.samples % self.block == 0:
                self._learn()
            start = stop
        return out


def _norm(rows: np.ndarray) -> np.ndarray:
    return np.sqrt(np.sum(np.asarray(rows) ** 2, axis=-1))


def _walk_through_disturbances(n: int, period_s: float) -> tuple[np.ndarray, np.ndarray]:
    """A device turning at random with an imperfectly calibrated field (uT) that passes a steel door (|B| up), a
    turn of the field (|B| kept) and a long stay in another place (the new normal)."""
    gyr = np.cumsum(RNG.normal(0.0, 0.15, (n, 3)), axis=0) * 0.1
    gyr += RNG.normal(0.0, 0.3, 3)
    earth = np.array([20.0, 0.0, 45.0])
    turned = _integrated(gyr, period_s, np.array([1.0, 0.0, 0.0, 0.0]))
    w, u = turned[:, :1], -turned[:, 1:]  # the earth's field into the body: the conjugate
    t = 2.0 * np.cross(u, earth)
    field = earth + w * t + np.cross(u, t)
    field = field @ (np.eye(3) + RNG.normal(0.0, 0.02, (3, 3))).T + RNG.normal(0.0, 0.3, (n, 3))
    field[n // 4 : n // 4 + 150] *= 1.4
    field[n // 2 : n // 2 + 300] = field[n // 2 : n // 2 + 300] @ np.array([[0.87, -0.5, 0], [0.5, 0.87, 0], [0, 0, 1]])
    field[3 * n // 4 :] *= 1.3
    return field, gyr


@pytest.mark.parametrize(
    "period_s, batch, n",
    # 500 Hz: a mean over 50 samples (a running sum in the kernel, summed afresh every ring's length); one sample a
    # batch over 20 s (the plain watch costs 0.17 ms a call): past learn_s, the three disturbances, 40 blocks
    [(0.01, 1, 2000), (0.01, 37, 4000), (0.02, 100, 4000), (0.01, 4000, 4000), (0.002, 500, 8000)],
)
def test_watch_update_is_the_plain_watch_whatever_the_batches(period_s, batch, n):
    field, gyr = _walk_through_disturbances(n, period_s)
    compiled, plain = FieldWatch(period_s), _PlainWatch(period_s)
    got, want = [], []
    for start in range(0, len(field), batch):
        got.append(compiled.update(field[start : start + batch], gyr[start : start + batch]))
        want.append(plain.update(field[start : start + batch], gyr[start : start + batch]))
        np.testing.assert_allclose(compiled.levels, plain.levels, rtol=1e-9, atol=1e-9)
        assert compiled.reference_ut == pytest.approx(plain.reference_ut, rel=1e-9, abs=1e-9)
    got_flags, want_flags = np.concatenate(got), np.concatenate(want)
    assert 0.05 < want_flags.mean() < 0.6  # the disturbances are flagged, the rest not: a test that can fail
    np.testing.assert_array_equal(got_flags, want_flags)


def test_watch_update_refuses_a_ring_of_the_wrong_size():
    watch = FieldWatch(0.01)
    watch.ring = np.zeros((3, 7))
    with pytest.raises(ValueError, match="ring"):
        watch.update(np.zeros((2, 3)), np.zeros((2, 3)))


def _with_specials(x: np.ndarray) -> np.ndarray:
    """``x`` with a few zeros, negative zeros, NaN (either sign), infinities and subnormals sprinkled in."""
    where = RNG.random(x.shape)
    for low, high, value in ((0.0, 0.02, 0.0), (0.02, 0.03, -0.0), (0.03, 0.035, np.nan), (0.035, 0.04, -np.nan),
                             (0.04, 0.045, np.inf), (0.045, 0.05, -np.inf), (0.05, 0.055, 1e-310)):  # fmt: skip
        x[(where >= low) & (where < high)] = value
    return x


def test_correct_field_is_numpys_einsum_of_each_batchs_matrix_to_the_bit():
    """Each batch's A (u - b) (``Correction.apply``) is ``np.einsum('sij,sj->si')`` of the matrices repeated per
    sample, bit for bit, NaN's sign included; uncalibrated batches (identity, zero offset) too."""
    count, batches = 60_000, 700
    mag = _with_specials(RNG.normal(0.0, 50.0, (count, 3)))
    sizes = RNG.multinomial(count, np.ones(batches) / batches)
    bounds = np.concatenate([[0], np.cumsum(sizes)]).astype(np.int64)
    offsets, matrices = (
        _with_specials(RNG.normal(0.0, 10.0, (batches, 3))),
        _with_specials(RNG.normal(size=(batches, 3, 3))),
    )
    matrices[::5], offsets[::5] = np.eye(3), 0.0
    with np.errstate(invalid="ignore"):
        want = np.einsum("sij,sj->si", np.repeat(matrices, sizes, axis=0), mag - np.repeat(offsets, sizes, axis=0))
    out = np.empty((count, 3))
    _kernels.correct_field(mag, offsets, matrices.reshape(batches, 9), bounds, out)
    assert np.array_equal(out.view(np.uint64), want.view(np.uint64))
    with pytest.raises(ValueError, match="out of range"):
        _kernels.correct_field(mag, offsets[:1], matrices[:1].reshape(1, 9), np.array([0, count + 1]), out)


def test_horizontal_force_is_numpys_einsum_of_the_first_two_rows_to_the_bit():
    count = 60_000
    rotation, acc = _with_specials(RNG.normal(size=(count, 3, 3))), _with_specials(RNG.normal(0.0, 9.0, (count, 3)))
    with np.errstate(invalid="ignore"):
        want = np.einsum("sij,sj->si", rotation[:, :2], acc) / 9.80665
    out = np.empty((count, 2))
    _kernels.horizontal_force(rotation.reshape(count, 9), acc, 9.80665, out)
    assert np.array_equal(out.view(np.uint64), want.view(np.uint64))
    finite, acc_ok = RNG.normal(size=(count, 3, 3)), RNG.normal(0.0, 9.0, (count, 3))  # the maths, plainly
    plain = np.stack([(finite[:, k] * acc_ok).sum(axis=1) for k in range(2)], axis=1) / 9.80665
    _kernels.horizontal_force(finite.reshape(count, 9), acc_ok, 9.80665, out)
    np.testing.assert_allclose(out, plain, rtol=1e-13, atol=1e-13)
