"""``magnet sample`` with the gyroscope sensors, emulated: gx,gy,gz (rad/s, body frame) and t_s columns that match
the moving simulator's truth."""

import csv
import io

import numpy as np
import pytest

from magnet import simulator as sim
from services.cli import main


@pytest.mark.parametrize("sensor", ["icm20948", "lsm9ds1", "mpu6050+hmc5883l", "mpu6050+qmc5883l"])
def test_sample_prints_the_gyroscope_in_the_body_frame(capsys, sensor):
    code = main(
        [
            "sample",
            "--sensor",
            sensor,
            "--emulate",
            "--count",
            "200",
            "--rate",
            "100",
            "--trajectory",
            "car",
            "--seed",
            "4",
            "--gyro-bias",
            "0.01,0,-0.02",
        ]
    )
    assert code == 0
    rows = list(csv.DictReader(io.StringIO(capsys.readouterr().out)))
    assert len(rows) == 200
    assert list(rows[0])[:10] == ["t_s", "mx", "my", "mz", "ax", "ay", "az", "gx", "gy", "gz"]
    t_s = np.array([float(r["t_s"]) for r in rows])
    np.testing.assert_allclose(t_s, np.arange(200) / 100.0)
    gyr = np.array([[float(r[k]) for k in ("gx", "gy", "gz")] for r in rows])
    truth = sim.simulate(
        sim.SimulatorConfig(
            trajectory="car",
            count=200,
            rate_hz=100.0,
            seed=4,
            errors=sim.SensorErrors(gyro_bias_rads=(0.01, 0.0, -0.02)),
        )
    )
    np.testing.assert_allclose(gyr, truth.gyr_rads, atol=0.002)


def test_sample_without_a_gyroscope_keeps_its_columns(capsys):
    assert main(["sample", "--sensor", "ak09918c+bma456", "--emulate", "--count", "3", "--trajectory", "car"]) == 0
    header = capsys.readouterr().out.splitlines()[0]
    assert header == "t_s,mx,my,mz,ax,ay,az,true_heading_deg,pitch_deg,roll_deg"
