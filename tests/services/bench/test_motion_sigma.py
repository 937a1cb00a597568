"""The heading uncertainty is honest where the bench says so: the multirotor through the compass's core, with and
without its velocity, has an RMS error within 0.7 .. 1.4 of its RMS sigma (``magnet bench motion`` prints every
trajectory); and every heading the core gives carries a finite sigma, on the wire too."""

import numpy as np
import pytest

from magnet import wire
from magnet.simulator import Trajectory
from services.bench import motion, motion_sigma


@pytest.mark.parametrize("aided", [True, False])
def test_the_multirotors_error_is_about_its_sigma(aided):
    [row] = motion_sigma.sigma_rows(motion.SimulatorSettings(seconds=60.0), [Trajectory.MULTIROTOR], aided)
    assert 0.7 <= row.ratio <= 1.4, (row.error_rms_deg, row.sigma_rms_deg)
    assert np.isfinite(row.sigmas).all() and (row.sigmas > 0).all()


def test_the_compass_core_puts_a_sigma_on_every_heading_message():
    settings = motion.SimulatorSettings(seconds=3.0)
    run = motion.moving_run(Trajectory.CAR, motion.simulated_sensor(settings), settings)
    calibration = wire.DeviceCalibration("sim", 0, motion._simulator_calibration(run, run.errors, settings)[0])
    heading, sigma = motion_sigma.compass_run(run, calibration)
    assert len(sigma) == len(heading) == len(run.t_s) and np.isfinite(sigma).all() and (sigma > 0).all()
    assert sigma.max() <= 180.0
