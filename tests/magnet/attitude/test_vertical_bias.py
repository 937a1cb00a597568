"""The aided filter's learning of the gyroscope's bias from the magnetometer: the Kalman filter of a vehicle's heading
drift (magnet.attitude.gyro_bias.HeadingDrift) and the integral term kept elsewhere
(magnet.attitude.aided_fusion.VerticalBias)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from magnet.attitude import aided_fusion, fusion
from magnet.attitude.aided_fusion import VerticalBias
from magnet.attitude.gyro_bias import Explained, HeadingDrift, PieceField
from magnet.attitude.heading import angle_difference_deg
from magnet.frames import to_magnetic_ned
from magnet.simulator import Trajectory
from services.bench.motion import SimulatorSettings, moving_run, simulated_sensor

SECONDS = 40.0  # the bias is learnt to 4e-5 rad/s by then; the error ratio 0.34 (0.64 vs 1.95 deg at 60 s)
SEED = 4


def test_the_loop_turns_a_steady_drift_of_delta_into_bias_along_the_up_axis_once_settled():
    loop = VerticalBias({"tauMag": 4.0}, 0.01)  # T_i = 8 s, settles after 4 s
    up = np.array([0.0, 0.6, 0.8])
    assert not loop.correction(0.0, up, 1.0, False).any()  # the first value only sets the reference
    assert not loop.correction(0.1, up, 1.0, False).any()  # 2 s fed: not settled yet
    for _ in range(2):
        loop.correction(0.2, up, 1.0, False)
    np.testing.assert_allclose(loop.correction(0.3, up, 1.0, False), -0.1 / 8.0 * up)  # delta grew 0.1 rad
    assert not loop.correction(0.5, up, 1.0, True).any()  # disturbed: not used, but the reference moves on
    np.testing.assert_allclose(loop.correction(0.5 + 2 * math.pi - 0.1, up, 1.0, False), 0.1 / 8.0 * up)  # wraps


def _heading_errors(run, field: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(heading errors (N,) deg of the causal aided filter fed in 1 s batches, its bias estimate (3,) body FRD)."""
    vel = to_magnetic_ned(np.asarray(run.vel_ned_ms), run.earth.declination_deg)
    filt = fusion.Fusion(0.01)
    headings = []
    for start in range(0, len(run.t_s), 100):
        part = slice(start, start + 100)
        out = filt.update(run.gyr_rads[part], run.acc_ms2[part], field[part], run.t_s[part], vel[part])
        headings.append(out.heading_deg)
    assert filt._aided is not None
    bias = np.asarray(filt._aided.filter.getBiasEstimate()[0]) * [1.0, -1.0, -1.0]  # vqf's z-up body -> FRD
    return angle_difference_deg(np.concatenate(headings), run.magnetic_heading_deg), bias


def test_a_multirotor_with_a_vertical_gyroscope_bias_converges_sooner(monkeypatch: pytest.MonkeyPatch):
    """A multirotor that never rests (seed 4's sensor: 0.55 deg/s about the vertical): without the drift filter
    vqf's heading lags the 6D drift by bias x tauMag until vqf learns the bias from the tilts."""
    settings = SimulatorSettings(seed=SEED, seconds=SECONDS)
    errors = simulated_sensor(settings)
    run = moving_run(Trajectory.MULTIROTOR, errors, settings)
    field = errors.true_calibration(run.earth.total_ut).apply(run.mag_ut)
    with_drift, bias = _heading_errors(run, field)
    monkeypatch.setattr(aided_fusion, "DRIFT_LEARNING", False)  # the compiled loop's switch for the drift filter
    without, _ = _heading_errors(run, field)
    scored = (run.t_s >= 10.0) & (np.abs(run.pitch_deg) < 60)
    rms_with, rms_without = (float(np.sqrt(np.mean(e[scored] ** 2))) for e in (with_drift, without))
    assert rms_with < 0.5 * rms_without, (rms_with, rms_without)  # measured 1.06 vs 3.15 deg at 40 s
    assert abs(bias[2] - errors.gyro_bias_rads[2]) < 0.001  # rad/s, the vertical (z) axis learnt


def test_the_drift_filter_learns_a_steady_turn_of_the_field_as_bias_about_the_vertical():
    """A level device whose 6D frame turns at 0.5 deg/s (a bias vqf missed): the field's heading in it turns the
    other way; fed back piece by piece, the rate learnt adds up to the bias along the up axis within seconds."""
    drift, up, rate = HeadingDrift(1.8, math.radians(0.5)), np.array([0.0, 0.0, 1.0]), math.radians(0.5)
    learnt, phi = np.zeros(3), 0.3
    rng = np.random.default_rng(0)
    for k in range(100):  # 10 s of pieces of 10 samples at 100 Hz
        t = 0.1 * k + np.arange(10) * 0.01
        heading = phi - (rate - learnt[2]) * (t - t[0] + 0.01)
        seen = heading + rng.normal(0.0, 0.01, 10)
        field = np.column_stack([np.sin(seen), np.cos(seen), np.full(10, -1.0)])  # dip 45 deg
        learnt += drift.update(_piece(t, field), False, up, 0.0)
        phi = float(heading[-1])
    assert learnt[2] == pytest.approx(rate, rel=0.1) and np.abs(learnt[:2]).max() < 1e-9
    assert not drift.update(_piece(np.arange(10) * 0.01 + 10.0, field), True, up, 0.0).any()  # disturbed: not used


def _piece(t_s: np.ndarray, field_earth: np.ndarray) -> PieceField:
    """The figures of a piece whose field (n, 3) is already in the earth frame (ENU), written plainly."""
    phi = np.arctan2(field_earth[:, 0], field_earth[:, 1])
    heading = math.atan2(float(np.mean(np.sin(phi))), float(np.mean(np.cos(phi))))
    horizontal = float(np.mean(np.hypot(field_earth[:, 0], field_earth[:, 1])))
    return PieceField(float(np.mean(t_s)), len(t_s), heading, horizontal, float(np.mean(field_earth[:, 2])))


def test_the_velocity_explains_a_vehicles_accelerometer_not_a_waved_hand():
    """What is left of the accelerometer, averaged: gravity alone leaves nothing, a 1 Hz swing the velocity
    cannot follow leaves its amplitude / sqrt(2) of the 0.1 s means."""
    up = np.tile([0.0, 0.0, 1.0], (10, 1))
    still, waved = Explained(), Explained()
    for k in range(600):
        t = 0.1 * k + np.arange(10) * 0.01
        assert still.update(_left(9.80665 * up, up), 0.1) < 1e-9
        swing = 4.0 * np.column_stack([np.sin(2 * np.pi * t), 0 * t, 0 * t])
        left = waved.update(_left(9.80665 * up + swing, up), 0.1)
    assert left == pytest.approx(4.0 / math.sqrt(2.0), rel=0.1)


def _left(acc: np.ndarray, up: np.ndarray) -> float:
    """|mean(acc - g up)| of a piece (m/s^2), written plainly."""
    return float(np.linalg.norm(np.mean(acc - 9.80665 * up, axis=0)))
