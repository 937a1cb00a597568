"""The compiled aided filter (magnet._kernels.aided_update, driving vqf's own C++ object) against the same filter
written plainly here: numpy, and vqf through its Python methods (the implementation before issue 28's compiled
loop). Simulated vehicles and random batch sizes; the answers must agree to rounding."""

from __future__ import annotations

import itertools
import math

import numpy as np
import pytest
import vqf
from test_kernels import _matrix, _product  # the plain maths the kernels are checked against

from magnet import _kernels
from magnet.attitude import aided_fusion, fusion
from magnet.attitude.aiding import DELAY_S, HALF_WINDOW_S, MAX_FIXES, STANDING_SPEED_MS, VEHICLE_RESIDUAL_MS2
from magnet.attitude.gyro_bias import (
    ANGLE_RANDOM_WALK,
    BIAS_RANDOM_WALK,
    EXPLAINED_TIME_S,
    HEADING_NOISE_DEG,
    MAX_DIP_DEG,
    TILT_ERROR_DEG,
)
from magnet.frames import to_magnetic_ned
from magnet.simulator import SimulatorConfig, Trajectory, simulate
from magnet.simulator.gnss import GnssSettings
from magnet.units import STANDARD_GRAVITY_MS2


def _vehicle_tau(residual: float, bias_sigma: float) -> float:
    sigma = residual / STANDARD_GRAVITY_MS2
    return (sigma**2 * 2.0 * HALF_WINDOW_S / (4.0 * bias_sigma**2)) ** (1.0 / 3.0)


class _PlainAided:
    """The aided filter as it was written in Python, plainly (one piece at a time through vqf's Python API)."""

    def __init__(self, period_s: float) -> None:
        self.period = period_s
        self.filter = vqf.VQF(period_s)
        defaults = self.filter.params
        self.tau_acc = float(defaults["tauAcc"])
        self.bias_sigma = math.radians(float(defaults["biasSigmaInit"]))
        self.vehicle_tau = min(_vehicle_tau(VEHICLE_RESIDUAL_MS2, self.bias_sigma), self.tau_acc)
        tau_mag = float(defaults["tauMag"])
        self.integral_s, self.settle_s = (
            aided_fusion.BIAS_INTEGRAL_TAUS * tau_mag,
            aided_fusion.BIAS_SETTLE_TAUS * tau_mag,
        )
        self.fed, self.disturbed = False, False
        self.times, self.values, self.held = np.zeros(0), np.zeros((0, 3)), None
        self.pending = np.zeros((0, 18))
        self.mean_square: float | None = None
        self.fed_s, self.delta = 0.0, None
        self._drift_reset()

    def _drift_reset(self) -> None:
        self.x, self.p, self.t_s, self.up = np.zeros(5), None, 0.0, np.array([0.0, 0.0, 1.0])

    # the fixes
    def _arrivals(self, vel: np.ndarray) -> np.ndarray:
        changed = np.empty(len(vel), dtype=bool)
        changed[0] = self.held is None or bool((vel[0] != self.held).any())
        changed[1:] = (vel[1:] != vel[:-1]).any(axis=1)
        return np.isfinite(vel).all(axis=1) & changed

    def _observe(self, t: np.ndarray, vel: np.ndarray) -> None:
        new = self._arrivals(vel)
        self.times = np.concatenate([self.times, t[new] - DELAY_S])[-MAX_FIXES:]
        self.values = np.concatenate([self.values, vel[new]])[-MAX_FIXES:]
        if np.isfinite(vel[-1]).all():
            self.held = vel[-1]

    def _acceleration(self, t: np.ndarray) -> np.ndarray:
        h = HALF_WINDOW_S
        if len(self.times) < 2:
            return np.zeros((len(t), 3))
        ahead = np.stack([np.interp(t + h, self.times, self.values[:, k]) for k in range(3)], -1)
        behind = np.stack([np.interp(t - h, self.times, self.values[:, k]) for k in range(3)], -1)
        covered = (t - h >= self.times[0]) & (t + h <= self.times[-1] + 1e-9)
        return np.where(covered[:, None], (ahead - behind) / (2 * h), 0.0)

    def _standing(self, start: float, end: float) -> bool | None:
        near = (self.times >= start - HALF_WINDOW_S) & (self.times <= end + HALF_WINDOW_S)
        if not near.any():
            return None
        return bool((np.linalg.norm(self.values[near], axis=1) < STANDING_SPEED_MS).all())

    # the answers
    def update(self, gyr, acc, field, t, vel) -> tuple[np.ndarray, np.ndarray]:
        rows = np.column_stack([t, gyr, acc, field, np.zeros((len(t), 8))])
        tick = np.floor(t / aided_fusion.CHUNK_S)
        cuts = np.flatnonzero(self._arrivals(vel)[1:] | (tick[1:] != tick[:-1])) + 1
        bounds = [0, *cuts.tolist(), len(rows)]
        parts = [self._chunk(rows[a:b], vel[a:b]) for a, b in itertools.pairwise(bounds)]
        return np.vstack([q for q, _ in parts]), np.concatenate([d for _, d in parts])

    def _chunk(self, rows: np.ndarray, vel: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        self._observe(rows[:, 0], vel)
        bias = np.asarray(self.filter.getBiasEstimate()[0])
        q = self.pending[-1, 14:18] if len(self.pending) else np.array([1.0, 0.0, 0.0, 0.0])
        for i, w in enumerate(rows[:, 1:4] - bias):  # right products of each period's turn
            norm = np.linalg.norm(w)
            half = norm * self.period / 2.0
            turn = np.concatenate([[np.cos(half)], w * (np.sin(half) / norm if norm > 0 else 0.0)])
            q = rows[i, 14:18] = _product(q, turn)
        self.pending = np.concatenate([self.pending, rows])
        self._give()
        if not self.fed:
            quat = self._feed(float(rows[0, 0]), 0, True)
            return quat[-len(rows) :], np.full(len(rows), self.disturbed)
        self._feed(float(rows[0, 0]), len(rows))
        self._give()
        return self.pending[-len(rows) :, 10:14].copy(), np.full(len(rows), self.disturbed)

    def _give(self) -> None:
        self.pending[:, 10:14] = _product(np.asarray(self.filter.getQuat9D()), self.pending[:, 14:18])

    def _feed(self, now: float, keep: int, at_once: bool = False) -> np.ndarray:
        known = self.times[-1] - HALF_WINDOW_S if len(self.times) >= 2 else -np.inf
        table = self.pending
        ready = (table[:, 0] <= known) | (table[:, 0] < now - aided_fusion.MAX_LAG_S) | at_once
        count = min(int(np.argmin(ready)) if not ready.all() else len(table), len(table) - keep)
        if count == 0:
            return np.zeros((0, 4))
        self.fed = True
        fed, self.pending = table[:count], table[count:].copy()
        a_ned = self._acceleration(fed[:, 0])
        a_enu = np.column_stack([a_ned[:, 1], a_ned[:, 0], -a_ned[:, 2]])
        acc = fed[:, 4:7] - np.einsum("nji,nj->ni", _matrix(fed[:, 10:14]), a_enu)
        gyr, field = np.ascontiguousarray(fed[:, 1:4]), np.ascontiguousarray(fed[:, 7:10])
        standing = self._standing(float(fed[0, 0]), float(fed[-1, 0]))
        self.filter.setRestBiasEstEnabled(standing is not False)
        out = self.filter.updateBatch(gyr, np.ascontiguousarray(acc), field)
        if standing is False:
            self._travelled(count * self.period)
        self.disturbed = bool(np.asarray(out["magDistDetected"])[-1])
        self._heading_loop(fed[:, 0], acc, field, out)
        if len(self.pending):
            turns = _product(fed[-1, 14:18] * [1, -1, -1, -1], self.pending[:, 14:18])
            self.pending[:, 14:18] = turns / np.linalg.norm(turns, axis=1, keepdims=True)
        return np.asarray(out["quat9D"])

    def _travelled(self, seconds: float) -> None:
        state, params = self.filter.state, self.filter.params
        norm, dip = np.asarray(state["magNormDip"]).reshape(-1)[:2]
        if not state["magDistDetected"] or state["magCandidateNorm"] <= 0.0:
            return
        if abs(norm - state["magCandidateNorm"]) < params["magNormTh"] * state["magCandidateNorm"] and abs(
            dip - state["magCandidateDip"]
        ) < math.radians(params["magDipTh"]):
            state["magCandidateT"] = float(state["magCandidateT"]) + seconds
            self.filter.state = state

    def _heading_loop(self, t, acc, field, out) -> None:
        rotations = _matrix(np.asarray(out["quat6D"]))
        earth = np.einsum("nij,nj->ni", rotations, field)
        up = rotations[-1, 2, :]
        phi = np.arctan2(earth[:, 0], earth[:, 1])
        heading = math.atan2(np.mean(np.sin(phi)), np.mean(np.cos(phi)))
        horizontal, vertical = float(np.mean(np.hypot(earth[:, 0], earth[:, 1]))), float(np.mean(earth[:, 2]))
        left = float(np.linalg.norm(np.mean(acc - STANDARD_GRAVITY_MS2 * rotations[:, 2, :], axis=0)))
        # vqf's flag, or the field watch's samples (a zero field, which vqf skips without raising its flag)
        watched = bool(np.any(np.all(field == 0.0, axis=1)))
        disturbed, seconds = bool(np.asarray(out["magDistDetected"]).any()) or watched, len(t) * self.period
        bias = np.asarray(self.filter.getBiasEstimate()[0])
        weight = -math.expm1(-seconds / EXPLAINED_TIME_S)
        square = left**2
        self.mean_square = (
            square if self.mean_square is None else self.mean_square + weight * (square - self.mean_square)
        )
        vehicle = _vehicle_tau(math.sqrt(self.mean_square), self.bias_sigma) < self.tau_acc
        tau = self.vehicle_tau if vehicle else self.tau_acc
        self.filter.setTauAcc(tau)
        if not vehicle:
            if self.p is not None:
                self._drift_reset()
            delta = float(self.filter.getDelta())
            self.fed_s += seconds
            step = 0.0
            if self.delta is not None and not disturbed and self.fed_s >= self.settle_s:
                step = math.remainder(delta - self.delta, math.tau)
            self.delta = delta
            self.filter.setBiasEstimate(bias - step / self.integral_s * up)
            return
        self.delta = None
        state = self.filter.state
        cov = np.asarray(state["biasP"]).reshape(3, 3)
        tilt = math.radians(math.sqrt(max(float(np.trace(cov) - up @ cov @ up), 0.0) / 2.0) / 100.0) * tau
        learnt = self._drift(float(np.mean(t)), len(t), heading, horizontal, vertical, disturbed, up, tilt, tau)
        if self.p is not None and not disturbed:
            state["bias"], state["delta"] = (bias + learnt).tolist(), float(self.x[0])
            self.filter.state = state
        else:
            self.filter.setBiasEstimate(bias + learnt)

    def _drift(self, t, count, z, horizontal, vertical, disturbed, up, tilt, tau) -> np.ndarray:
        dip = min(math.atan2(abs(vertical), horizontal), math.radians(MAX_DIP_DEG))
        sigma_c = math.hypot(math.radians(TILT_ERROR_DEG), tilt) * math.tan(dip)
        if self.p is None:
            if not disturbed:
                self.x, self.t_s, self.up = np.array([z, 0.0, 0.0, 0.0, 0.0]), t, up
                self.p = np.diag([math.radians(HEADING_NOISE_DEG) ** 2, *[self.bias_sigma**2] * 3, sigma_c**2])
            return np.zeros(3)
        dt = max(t - self.t_s, 0.0)
        decay = math.exp(-dt / tau)
        f = np.eye(5)
        f[0, 1:4] = -dt * (up + self.up) / 2.0
        f[4, 4] = decay
        noise = [ANGLE_RANDOM_WALK**2 * dt, *[BIAS_RANDOM_WALK**2 * dt] * 3, sigma_c**2 * (1.0 - decay**2)]
        self.x, self.p = f @ self.x, f @ self.p @ f.T + np.diag(noise)
        if not disturbed:
            h = np.array([1.0, 0.0, 0.0, 0.0, 1.0])
            s = h @ self.p @ h + math.radians(HEADING_NOISE_DEG) ** 2 / count
            gain = self.p @ h / s
            self.x = self.x + gain * math.remainder(z - h @ self.x, math.tau)
            self.x[0] = math.remainder(self.x[0], math.tau)
            self.p = self.p - np.outer(gain, h @ self.p)
        self.t_s, self.up = t, up
        if disturbed:
            return np.zeros(3)
        learnt = self.x[1:4].copy()
        self.x[1:4] = 0.0
        return learnt


def _vehicle(trajectory: Trajectory, fix_hz: float, seed: int) -> tuple[np.ndarray, ...]:
    run = simulate(
        SimulatorConfig(trajectory=trajectory, rate_hz=100.0, count=2500, seed=seed, gnss=GnssSettings(rate_hz=fix_hz))
    )
    field = run.errors.true_calibration(float(run.earth.total_ut)).apply(run.mag_ut)
    vel = to_magnetic_ned(np.asarray(run.vel_ned_ms), run.earth.declination_deg)
    return (*(fusion.to_vqf_frame(x) for x in (run.gyr_rads, run.acc_ms2, field)), run.t_s, vel)


@pytest.mark.parametrize(
    ("trajectory", "fix_hz", "seed"),
    [(Trajectory.CAR, 5.0, 11), (Trajectory.MULTIROTOR, 100.0, 12), (Trajectory.FIGURE8, 10.0, 13)],
)
def test_the_compiled_aided_filter_is_the_plain_one_whatever_the_batches(trajectory, fix_hz, seed):
    gyr, acc, field, t, vel = _vehicle(trajectory, fix_hz, seed)
    rng = np.random.default_rng(seed)
    plain, compiled = _PlainAided(0.01), aided_fusion.AidedFilter(0.01, {})
    lo = 0
    while lo < len(t):
        part = slice(lo, lo + int(rng.integers(1, 150)))
        q_plain, d_plain = plain.update(gyr[part], acc[part], field[part], t[part], vel[part])
        q_compiled, d_compiled = compiled.update(gyr[part], acc[part], field[part], t[part], vel[part])
        np.testing.assert_allclose(q_compiled, q_plain, atol=1e-9, err_msg=f"samples {part}")
        np.testing.assert_array_equal(d_compiled, d_plain)
        lo = part.stop
    assert compiled.drift.p is not None or trajectory is not Trajectory.CAR  # a car's drift filter ran
    np.testing.assert_allclose(compiled.filter.getBiasEstimate()[0], plain.filter.getBiasEstimate()[0], atol=1e-12)


def _watched(field: np.ndarray, t: np.ndarray, start_s: float, seconds: float) -> np.ndarray:
    """The field with the samples of [start_s, start_s + seconds) zeroed, as the field watch hands them to vqf."""
    return np.where(((t >= start_s) & (t < start_s + seconds))[:, None], 0.0, field)


def test_the_compiled_aided_filter_is_the_plain_one_with_watched_samples():
    gyr, acc, field, t, vel = _vehicle(Trajectory.CAR, 5.0, 11)
    field = _watched(_watched(field, t, 12.0, 0.6), t, 18.03, 0.05)
    plain, compiled = _PlainAided(0.01), aided_fusion.AidedFilter(0.01, {})
    for lo in range(0, len(t), 25):
        part = slice(lo, lo + 25)
        q_plain, _ = plain.update(gyr[part], acc[part], field[part], t[part], vel[part])
        q_compiled, _ = compiled.update(gyr[part], acc[part], field[part], t[part], vel[part])
        np.testing.assert_allclose(q_compiled, q_plain, atol=1e-9, err_msg=f"samples {part}")


def test_samples_the_watch_took_the_field_from_do_not_turn_a_vehicles_heading():
    """The watch hands vqf a zero field where the field is suspect (vqf skips it, its own flag down); the drift
    filter's piece heading read those samples as north (atan2(0, 0)): on the bench's boat of seed 88 an in-service
    record that moved the field by 8 deg had its step watched for 0.6 s, and the heading went 30 deg off."""
    gyr, acc, field, t, vel = _vehicle(Trajectory.CAR, 5.0, 11)
    headings = []
    for given in (field, _watched(field, t, 15.0, 0.6)):
        aided = aided_fusion.AidedFilter(0.01, {})
        quat = np.vstack([aided.update(gyr[lo : lo + 25], acc[lo : lo + 25], given[lo : lo + 25], t[lo : lo + 25],
                                       vel[lo : lo + 25])[0] for lo in range(0, len(t), 25)])  # fmt: skip
        rotations = _matrix(quat)
        headings.append(np.degrees(np.arctan2(rotations[:, 1, 0], rotations[:, 0, 0])))
    after = t >= 15.0
    apart = np.abs(np.degrees(np.angle(np.exp(1j * np.radians(headings[1][after] - headings[0][after])))))
    assert apart.max() < 1.0


def test_the_vqf_fields_read_through_its_cpp_object_are_its_state():
    gyr, acc, field, t, vel = _vehicle(Trajectory.CAR, 5.0, 14)
    aided = aided_fusion.AidedFilter(0.01, {})
    aided.update(gyr, acc, field, t, vel)
    probe, state, params = _kernels.vqf_probe(aided.filter), aided.filter.state, aided.filter.params
    for key in ("delta", "magCandidateNorm", "magCandidateDip", "magCandidateT"):
        assert probe[key] == float(state[key]), key
    assert probe["magDistDetected"] == bool(state["magDistDetected"])
    np.testing.assert_array_equal(probe["bias"], np.asarray(state["bias"]).reshape(3))
    np.testing.assert_array_equal(probe["biasP"], np.asarray(state["biasP"]).reshape(9))
    np.testing.assert_array_equal(probe["magNormDip"], np.asarray(state["magNormDip"]).reshape(2))
    for key in ("magNormTh", "magDipTh", "tauAcc", "restBiasEstEnabled"):
        assert probe[key] == params[key], key


def test_only_a_vqf_filter_is_driven():
    aided = aided_fusion.AidedFilter(0.01, {})
    with pytest.raises(TypeError, match=r"expected a vqf\.VQF"):
        _kernels.vqf_travelled(object(), 1.0)
    t, zeros = np.arange(5) * 0.01, np.zeros((5, 3))
    with pytest.raises(ValueError, match="pending has room"):
        _kernels.aided_update(
            aided.filter, aided.settings, aided.state, aided.fixes.buffer_times, aided.fixes.buffer_values,
            np.zeros((2, 18)), t, zeros, zeros, zeros, zeros, np.zeros((5, 4)), np.zeros(5, dtype=bool),
        )  # fmt: skip
