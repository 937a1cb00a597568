"""The edge's sources without Zenoh: what a batch carries."""

import numpy as np
import pytest

from services.edge.settings import EdgeSettings
from services.edge.sources import ChipSource, make_source


@pytest.mark.parametrize(
    "sensor,acc,gyr",
    [
        ("hmc5883l", False, False),
        ("lsm303dlh", True, False),
        ("icm20948", True, True),
        ("mpu6050+qmc5883l", True, True),
    ],
)
def test_an_emulated_chip_batch_carries_what_the_chip_measures(sensor, acc, gyr):
    source = make_source(EdgeSettings(device="c-1", sensor=sensor, emulate=True, rate_hz=100.0, batch=5))
    assert isinstance(source, ChipSource)
    [batch] = source.take(7, 0, lambda: False)
    assert batch.device == "c-1" and batch.seq == 7 and batch.sensor == sensor and len(batch) == 5
    assert np.all(np.isfinite(batch.mag_ut)) and 20 < np.median(np.linalg.norm(batch.mag_ut, axis=1)) < 70
    assert (batch.acc_ms2 is not None) == acc and (batch.gyr_rads is not None) == gyr
    assert source.status()["samples"] == 5 and source.status()["errors"] == 0


def test_a_stopped_dead_chip_gives_no_batch():
    source = make_source(EdgeSettings(device="c-2", sensor="hmc5883l", emulate=True, emulate_faults=1.0))
    assert source.take(0, 0, lambda: True) == [] and source.status()["attempts"] == 0
