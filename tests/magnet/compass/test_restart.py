"""A new calibration restarts the device's filter only when it moves the field (``calibrations.small_change``): an
in-service refresh that turns the field by a degree keeps the filter, a new hard iron restarts it."""

from __future__ import annotations

import numpy as np

from magnet.compass.calibrations import small_change
from magnet.model import Calibration

OLD = Calibration(method="offset", offset=np.array([300.0, -200.0, 100.0]), matrix=np.eye(3), field_strength=50.0)


def test_a_refresh_that_hardly_moves_the_field_keeps_the_filter_and_a_new_iron_does_not():
    assert small_change(OLD, OLD.replace(offset=OLD.offset + [0.5, -0.3, 0.4]))
    assert small_change(OLD, OLD.replace(matrix=np.diag([1.01, 0.99, 1.0])))
    assert not small_change(OLD, OLD.replace(offset=OLD.offset + [6.0, 0.0, 0.0]))  # 7 deg at worst
    assert not small_change(OLD, OLD.replace(matrix=np.diag([1.1, 1.0, 1.0])))  # 10 % stronger along x
    assert not small_change(OLD, OLD.replace(unit="gauss"))
