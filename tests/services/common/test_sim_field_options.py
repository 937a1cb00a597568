"""The simulator's field options (``--disturbances``, ``--iron-change``) of ``magnet sample`` and ``magnet edge``."""

import argparse

import numpy as np
import pytest

from services.common.sim_options import SimulatorSettings, add_simulator_arguments


def settings(*argv: str) -> SimulatorSettings:
    parser = argparse.ArgumentParser()
    add_simulator_arguments(parser)
    return SimulatorSettings.from_args(parser.parse_args(list(argv)))


def test_a_walk_past_doors_whose_hard_iron_changes():
    chosen = settings("--trajectory", "walk-hand", "--disturbances", "--iron-change", "2,100,-50,20")
    stream = chosen.sensor_stream(200, 50.0)
    samples = np.array([stream.measure_imu()[0] for _ in range(200)])
    same = settings("--trajectory", "walk-hand", "--disturbances").sensor_stream(200, 50.0)
    np.testing.assert_allclose(samples[:100], [same.measure_imu()[0] for _ in range(100)])  # the same walk until then
    jump = np.linalg.norm(samples[101] - samples[99])
    assert jump > 50.0  # the hard iron moved from none to (100, -50, 20) uT at 2 s
    assert settings().config_extras() == {"disturbances": None, "hard_iron_change": None}


@pytest.mark.parametrize(
    ("argv", "message"),
    [
        (["--trajectory", "tumble", "--disturbances"], "along a path"),
        (["--trajectory", "walk-hand", "--iron-change", "1,2"], "4 numbers"),
        (["--trajectory", "walk-hand", "--iron-change=-1,0,0,0"], ">= 0"),
    ],
)
def test_bad_field_options_are_refused(argv, message):
    with pytest.raises(ValueError, match=message):
        settings(*argv)
