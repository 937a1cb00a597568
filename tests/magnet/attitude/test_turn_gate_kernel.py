"""The turn gate's compiled maths (magnet._kernels.gate_update, gated_run) against the gate written plainly here in
numpy (the Python implementation it replaced, and the swing's levelling written from its docstrings), on random
walkers', runners' and arm swingers' samples cut into random batches."""

from __future__ import annotations

import math

import numpy as np
import pytest
import vqf

from magnet.attitude.turn_gate import TurnGate, TurnSettings, run_gated


def _turned_by(start: np.ndarray, gyr: np.ndarray, bias: np.ndarray, period_s: float) -> np.ndarray:
    """(n, 4): ``start`` (4,) carried forward by each rate less ``bias`` over one period (right products), plainly
    (in Python floats: numpy's calls on one quaternion at a time cost ten times the maths)."""
    out, (w, x, y, z) = [], start.astype(float).tolist()
    for rx, ry, rz in (gyr - bias).tolist():
        norm = math.sqrt(rx * rx + ry * ry + rz * rz)
        half = norm * period_s / 2.0
        s = math.sin(half) / norm if norm > 0 else 0.0
        a, b, c, d = math.cos(half), rx * s, ry * s, rz * s
        w, x, y, z = (
            w * a - x * b - y * c - z * d,
            w * b + x * a + y * d - z * c,
            w * c - x * d + y * a + z * b,
            w * d + x * c - y * b + z * a,
        )
        out.append((w, x, y, z))
    return np.array(out, dtype=float).reshape(-1, 4)


def _to_frame(quat: np.ndarray, vectors: np.ndarray) -> np.ndarray:
    """Each vector (n, 3) rotated by its quaternion (n, 4) as v + 2 w (u x v) + 2 u x (u x v), plainly."""
    w, u = quat[:, :1], quat[:, 1:]
    t = 2.0 * np.cross(u, vectors)
    return vectors + w * t + np.cross(u, t)


class PlainGate:
    """TurnGate's maths (its docstrings are the specification) in numpy, one block's piece at a time."""

    def __init__(self, gate: TurnGate) -> None:
        self.g = gate  # its settings only
        w = gate.width
        self.recent, self.stride, self.run, self.samples = np.zeros(2 * (w - 1)), w, 0, 0
        self.earth_acc, self.magnitudes = np.full((w - 1, 3), np.nan), np.full(gate.gait_width, np.nan)
        self.rates = np.full((gate.gait_width, 3), np.nan)
        self.held, self.attitude, self.bias = np.array([1.0, 0, 0, 0]), np.zeros(4), np.zeros(3)
        self.in_gait = self.in_swing = False

    def update(self, gyr, acc, start, bias):
        g, period = self.g, self.g.period_s
        if self.samples % g.block == 0:
            self.attitude, self.bias, before = start, bias, self.stride
            swing = self._swing()
            if swing == 2:  # fast: a swing where the magnitudes are a gait too (their stride not taken), else neither
                stride = self.stride
                self.in_swing, self.in_gait = self._gait(), False
                self.stride = stride if self.in_swing else before
            else:
                self.in_swing = swing == 1
                self.in_gait = not self.in_swing and self._gait()
        self.samples += len(gyr)
        attitude = _turned_by(self.attitude, gyr, self.bias, period)
        self.attitude = attitude[-1]
        up_body = _to_frame(attitude * [1.0, -1.0, -1.0, -1.0], np.tile([0.0, 0.0, 1.0], (len(gyr), 1)))
        seen = np.concatenate([self.recent, _to_frame(attitude, gyr - self.bias)[:, 2] * period])
        self.recent = seen[len(gyr) :]
        n = self.stride
        kernel = np.concatenate([np.arange(1, n + 1), np.arange(n - 1, 0, -1)]) / n
        first = len(seen) - len(gyr) - (g.width - 1) - (n - 1)
        turned = np.convolve(seen[first : len(seen) - (g.width - 1) + n - 1], kernel, mode="valid")
        held = _turned_by(self.held, gyr, self.bias, period)
        self.held = held[-1] / np.linalg.norm(held[-1])
        earth = np.concatenate([self.earth_acc, _to_frame(held, acc)])
        delayed, self.earth_acc = earth[: len(acc)], earth[len(acc) :]
        self.magnitudes = np.concatenate([self.magnitudes, np.linalg.norm(acc, axis=1)])[-g.gait_width :]
        self.rates = np.vstack([self.rates, gyr])[-g.gait_width :]
        if self.in_swing:
            return self._level(seen, earth, held, _to_frame(held, up_body), acc), np.zeros(len(gyr), dtype=bool)
        gated = np.zeros(len(gyr), dtype=bool)
        for i, over in enumerate(np.abs(np.degrees(turned)) > g.settings.turn_deg):
            self.run = self.run + 1 if over and self.in_gait else 0
            gated[i] = self.run > 0 and self.run <= g.max_hold
        if not self.in_gait:
            return acc, gated
        fed = _to_frame(held * [1.0, -1.0, -1.0, -1.0], delayed)
        fresh = np.isnan(fed[:, 0])
        fed[fresh] = acc[fresh]
        fed[gated] = 0.0
        return fed, gated

    def _level(self, seen, earth, held, up, acc):
        """In a swing: where the triangle-weighted rotation about the vertical over the last two strides exceeds
        turn_deg, the specific force less the horizontal part of its mean over the last stride (held frame)."""
        n, w1, fed = self.stride, self.g.width - 1, acc.copy()
        kernel = np.concatenate([np.arange(1, n + 1), np.arange(n - 1, 0, -1)]) / n
        for j in range(len(acc)):
            turned = seen[2 * w1 + j - (2 * n - 2) : 2 * w1 + j + 1] @ kernel
            over = abs(np.degrees(turned)) > self.g.settings.turn_deg
            self.run = self.run + 1 if over else 0
            if not (over and self.run <= self.g.max_hold):
                continue
            mean = earth[w1 + j - n + 1 : w1 + j + 1].mean(axis=0)
            if np.isnan(mean).any():
                continue
            u = up[j] / np.linalg.norm(up[j])
            level = mean - (mean @ u) * u
            fed[j] = acc[j] - _to_frame(held[j : j + 1] * [1.0, -1.0, -1.0, -1.0], level[None])[0]
        return fed

    def _swing(self) -> int:
        if np.isnan(self.rates[0, 0]):
            return 0
        centred = self.rates - self.rates.mean(axis=0)
        power = float(np.sum(centred * centred))
        settings = self.g.settings
        if not settings.swing_sd_rads**2 < power / len(centred) < settings.swing_max_rads**2:
            return 0
        strides = self.g.stride_lags[self.g.stride_lags < len(centred)]
        correlation = np.array([np.sum(centred[: len(centred) - k] * centred[k:]) for k in strides])
        if correlation.max() <= self.g.settings.swing_corr * power:
            return 0
        self.stride = min(self.g.width, int(strides[np.argmax(correlation)]))
        return 2 if power >= len(centred) * settings.swing_gait_rads**2 else 1

    def _gait(self) -> bool:
        if np.isnan(self.magnitudes[0]):
            return False
        centred = self.magnitudes - self.magnitudes.mean()
        power = float(centred @ centred)
        if power <= len(centred) * self.g.settings.gait_sd_ms2**2:
            return False
        correlation = np.array([centred[: len(centred) - k] @ centred[k:] for k in range(len(centred))])
        strides = self.g.stride_lags[self.g.stride_lags < len(centred)]
        if max(correlation[self.g.lags].max(), correlation[strides].max()) <= self.g.settings.gait_corr * power:
            return False
        self.stride = min(self.g.width, int(strides[np.argmax(correlation[strides])]))
        return True


def walker(rng: np.random.Generator, count: int, period_s: float) -> tuple[np.ndarray, np.ndarray]:
    """Body rates and specific forces (count, 3) of a random walker or runner: straights and corners, a bounce at
    a random step rate (vanishing for a while: standing), noise; not a physical simulation, just gait-like."""
    t = np.arange(count) * period_s
    step_hz, bounce = rng.uniform(1.5, 3.2), rng.uniform(1.5, 6.0)
    gyr = rng.normal(0.0, 0.05, (count, 3)) + rng.normal(0.0, 0.02, 3)
    corners = rng.integers(0, count, 6)
    for c in corners:  # 45 to 180 deg in 0.7 to 2 s
        width = int(rng.uniform(0.7, 2.0) / period_s)
        gyr[c : c + width, 2] += np.radians(rng.choice([-1, 1]) * rng.uniform(45, 180)) / (width * period_s)
    gyr[:, :2] += 0.6 * np.sin(2 * np.pi * step_hz / 2 * t)[:, None] * rng.normal(0, 1, 2)  # the trunk's sway
    acc = rng.normal(0.0, 0.3, (count, 3))
    acc[:, 2] += 9.81 + bounce * np.sin(2 * np.pi * step_hz * t) * (t % 30 < 22)  # stands 8 s every 30
    acc[:, :2] += rng.normal(0, 0.5, 2)  # held tilted
    return gyr, acc


def swinger(
    rng: np.random.Generator, count: int, period_s: float, peak_rads: tuple[float, float] = (2.5, 4.0)
) -> tuple[np.ndarray, np.ndarray]:
    """A walker's corners (as ``walker``) with an arm's swing: body rates about a random axis at a random stride
    rate (``peak_rads``, stopping for a while), the specific force swinging with it; no steps' bounce."""
    gyr, acc = walker(rng, count, period_s)
    t = np.arange(count) * period_s
    stride_hz, axis = rng.uniform(0.8, 1.6), rng.normal(size=3)
    swing = rng.uniform(*peak_rads) * np.sin(2 * np.pi * stride_hz * t) * (t % 15 < 12)
    gyr += swing[:, None] * axis / np.linalg.norm(axis)
    acc[:, 2] = 9.81 + rng.normal(0.0, 0.3, count)
    acc[:, :2] += 3.0 * np.cos(2 * np.pi * stride_hz * t)[:, None] * rng.normal(0, 1, 2)
    return gyr, acc


def fast_turner(rng: np.random.Generator, count: int, period_s: float) -> tuple[np.ndarray, np.ndarray]:
    """A swinger whose rates swing as fast as a runner's arm (7 to 9.5 rad/s peak), without steps: no swing."""
    return swinger(rng, count, period_s, (7.0, 9.5))


def runner(rng: np.random.Generator, count: int, period_s: float) -> tuple[np.ndarray, np.ndarray]:
    """A walker's steps and corners (as ``walker``) with a runner's arm swinging (7 to 9.5 rad/s peak, about a
    random axis at the stride rate, stopping for a while): a swing, its steps a gait."""
    gyr, acc = walker(rng, count, period_s)
    t = np.arange(count) * period_s
    stride_hz, axis = rng.uniform(1.2, 1.6), rng.normal(size=3)
    swing = rng.uniform(7.0, 9.5) * np.sin(2 * np.pi * stride_hz * t) * (t % 15 < 12)
    return gyr + swing[:, None] * axis / np.linalg.norm(axis), acc


@pytest.mark.parametrize(
    ("period_s", "seed", "moves"),
    [(0.01, 1, walker), (0.02, 2, walker), (0.013, 3, walker), (0.005, 4, walker), (0.02, 5, swinger),
     (0.01, 6, swinger), (0.02, 7, runner), (0.01, 8, fast_turner)],
)  # fmt: skip
def test_gate_update_is_the_plain_gate_whatever_the_batches(period_s, seed, moves):
    rng = np.random.default_rng(seed)
    gyr, acc = moves(rng, round((20.0 if moves is swinger else 60.0) / period_s), period_s)
    gate = TurnGate(period_s, TurnSettings(max_hold_s=3.0))
    plain = PlainGate(gate)
    fed_c, gated_c, fed_p, gated_p, gaits, swings, levelled = [], [], [], [], 0, 0, 0
    start = 0
    while start < len(gyr):
        stop = min(start + int(rng.integers(1, gate.left_in_block() + 1)), len(gyr))
        q = rng.normal(size=4)
        q, bias = q / np.linalg.norm(q), rng.normal(0.0, 0.01, 3)
        for out, (fed, gated) in (
            ((fed_c, gated_c), gate.update(gyr[start:stop], acc[start:stop], q, bias)),
            ((fed_p, gated_p), plain.update(gyr[start:stop], acc[start:stop], q, bias)),
        ):
            out[0].append(fed)
            out[1].append(gated)
        assert (gate.in_gait, gate.in_swing, gate.stride, gate.run, gate.samples) == (
            plain.in_gait,
            plain.in_swing,
            plain.stride,
            plain.run,
            plain.samples,
        )
        gaits += gate.in_gait
        swings += gate.in_swing
        levelled += int(np.any(fed_c[-1] != acc[start:stop])) if gate.in_swing else 0
        start = stop
    if moves is walker:
        assert gaits > 0 and np.concatenate(gated_c).any()  # the gate was at work: gaits, turns left out
    elif moves is runner:  # the arm swinging: a swing, turns levelled; while it stops, a gait
        assert swings > 0 and levelled > 0 and gaits > 0
    elif moves is fast_turner:  # rates as fast as a runner's arm, no steps: neither
        assert swings == 0 and levelled == 0
    else:  # swings, turns levelled, nothing left out
        assert swings > 0 and levelled > 0 and not np.concatenate(gated_c).any()
    np.testing.assert_array_equal(np.concatenate(gated_c), np.concatenate(gated_p))
    np.testing.assert_allclose(np.vstack(fed_c), np.vstack(fed_p), rtol=0, atol=1e-9)
    np.testing.assert_allclose(gate.recent, plain.recent, rtol=0, atol=1e-12)
    np.testing.assert_allclose(gate.earth_acc, plain.earth_acc, rtol=0, atol=1e-9)
    np.testing.assert_allclose(gate.magnitudes, plain.magnitudes, rtol=0, atol=1e-12)
    np.testing.assert_allclose(gate.rates, plain.rates, rtol=0, atol=0)


def gated_in_batches(compiled: bool, gyr, acc, field, period_s: float) -> list[np.ndarray]:
    """vqf's quaternions (9D with a field, else 6D) and flags through the gate, in batches of 1 to 150 samples."""
    gate, filter_ = TurnGate(period_s), vqf.VQF(period_s)
    rng, parts, start = np.random.default_rng(6), [], 0
    keys = ("quat9D", "restDetected", "magDistDetected") if field is not None else ("quat6D", "restDetected")
    while start < len(gyr):
        rows = slice(start, min(start + int(rng.integers(1, 151)), len(gyr)))
        piece = None if compiled else (lambda g, a, f, _w: filter_.updateBatch(g, a, f))
        samples = (gyr[rows], acc[rows], None if field is None else field[rows])
        out = run_gated(gate, filter_, piece, samples, np.zeros(rows.stop - rows.start, dtype=bool))
        parts.append([np.asarray(out[key]) for key in keys])
        start = rows.stop
    assert gate.samples == len(gyr)
    return [np.concatenate([part[k] for part in parts]) for k in range(len(keys))]


@pytest.mark.parametrize("with_field", [True, False])
@pytest.mark.parametrize("moves", [walker, swinger])
def test_gated_run_drives_vqf_as_the_gate_and_updatebatch_piece_by_piece(with_field, moves):
    rng = np.random.default_rng(5)
    gyr, acc = moves(rng, 4000, 0.01)
    field = np.ascontiguousarray(rng.normal(0, 0.3, (4000, 3)) + [20.0, 0.0, -40.0]) if with_field else None
    compiled, plain = (gated_in_batches(c, gyr, acc, field, 0.01) for c in (True, False))
    for c, p in zip(compiled, plain):
        if c.dtype == bool:
            np.testing.assert_array_equal(c, p)
        else:
            np.testing.assert_allclose(c, p, rtol=0, atol=1e-12)


def test_gated_run_refuses_what_it_cannot_read():
    gate, filter_ = TurnGate(0.01), vqf.VQF(0.01)
    gyr = np.zeros((10, 3))
    with pytest.raises(ValueError, match="acc"):
        run_gated(gate, filter_, None, (gyr, np.zeros((9, 3)), None), np.zeros(10, bool))
    with pytest.raises(ValueError, match="gyr"):
        run_gated(gate, filter_, None, (np.zeros((10, 3))[:, ::-1], np.zeros((10, 3)), None), np.zeros(10, bool))
    with pytest.raises(TypeError, match=r"vqf\.VQF"):
        run_gated(gate, object(), None, (gyr, gyr, None), np.zeros(10, bool))
