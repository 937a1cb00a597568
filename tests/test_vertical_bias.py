"""The aided filter's integral term for the gyroscope's bias about the vertical (magnet.aided_fusion.VerticalBias)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from magnet import aided_fusion, fusion
from magnet.aided_fusion import VerticalBias
from magnet.frames import to_magnetic_ned
from magnet.heading import angle_difference_deg
from magnet.simulator import Trajectory
from services.bench.motion import SimulatorSettings, moving_run, simulated_sensor

SECONDS = 60.0
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
    """A multirotor that never rests (seed 4's sensor: 0.55 deg/s about the vertical): without the integral term
    vqf's heading lags the 6D drift by bias x tauMag until vqf learns the bias from the tilts."""
    settings = SimulatorSettings(seed=SEED, seconds=SECONDS)
    errors = simulated_sensor(settings)
    run = moving_run(Trajectory.MULTIROTOR, errors, settings)
    field = errors.true_calibration(run.earth.total_ut).apply(run.mag_ut)
    with_loop, bias = _heading_errors(run, field)
    monkeypatch.setattr(aided_fusion, "BIAS_INTEGRAL_TAUS", math.inf)
    without, _ = _heading_errors(run, field)
    scored = (run.t_s >= 10.0) & (np.abs(run.pitch_deg) < 60)
    rms_with, rms_without = (float(np.sqrt(np.mean(e[scored] ** 2))) for e in (with_loop, without))
    assert rms_with < 0.85 * rms_without, (rms_with, rms_without)  # measured 2.07 vs 2.68 deg
    assert abs(bias[2] - errors.gyro_bias_rads[2]) < 0.001  # rad/s, the vertical (z) axis learnt
