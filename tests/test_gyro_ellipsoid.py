"""Calibration from the gyroscope (magnet.calibration.gyro_ellipsoid) against simulator truth."""

from __future__ import annotations

import dataclasses
import time

import numpy as np
import pytest

from magnet.calibration import FitError
from magnet.calibration.gyro_ellipsoid import fit_gyro_ellipsoid
from magnet.simulator import SensorErrors, SimulatorConfig, Trajectory, simulate


@pytest.fixture(scope="module")
def tumbled():
    rng = np.random.default_rng(4)
    errors = SensorErrors.random(
        rng, 50.0, hard_iron_max_ratio=1.0, soft_iron_max=0.1, noise_ut=0.3, gyro_noise_rads=0.002
    )
    errors = dataclasses.replace(errors, misalignment_deg=(2.0, -3.0, 4.0))
    run = simulate(SimulatorConfig(trajectory=Trajectory.FAST_TUMBLE, rate_hz=100.0, count=30_000, errors=errors))
    return run, errors.true_calibration(run.earth.total_ut)


def test_offset_soft_iron_and_the_rotation_into_the_imu_frame_come_back(tumbled):
    run, truth = tumbled
    started = time.perf_counter()
    offset, matrix = fit_gyro_ellipsoid(run.mag_ut, run.gyr_rads, 0.01, field_ut=run.earth.total_ut)
    assert time.perf_counter() - started < 1.0  # 5 minutes at 100 Hz
    np.testing.assert_allclose(offset, truth.offset, atol=0.1)  # uT, hard iron up to the field itself
    # the matrix holds the 2-4 deg misalignment (an ellipsoid fit cannot see it): recovered to 0.5 %
    assert np.abs(matrix - truth.matrix).max() < 0.005 * np.abs(truth.matrix).max()


def test_rotation_about_one_axis_is_refused_with_what_to_do():
    t = np.arange(3000) * 0.01
    angle = 0.5 * t
    earth = np.array([20.0, 0.0, 45.0])
    mag = np.stack([np.cos(angle) * earth[0], -np.sin(angle) * earth[0], np.full_like(t, earth[2])], axis=-1)
    gyr = np.tile([0.0, 0.0, 0.5], (len(t), 1))
    with pytest.raises(FitError, match="every axis"):
        fit_gyro_ellipsoid(mag + 10.0, gyr, 0.01)
    with pytest.raises(FitError, match="same shape"):
        fit_gyro_ellipsoid(mag, gyr[:10], 0.01)
