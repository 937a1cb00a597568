"""The heading's sigma on ROS 2 (pure side): the Imu's orientation covariance holds the tilts and the yaw in rad^2
on its diagonal where the orientation is given (and stays "not given" where it is not); the device's diagnostic
carries the sigma and warns beyond ``UNCERTAIN_HEADING_DEG``."""

import math

import numpy as np
from rosbags.typesys import Stores, get_typestore

from magnet.ros2 import compass as rc
from magnet.ros2 import messages

JAZZY = get_typestore(Stores.ROS2_JAZZY)


def test_the_imu_orientation_covariance_is_the_tilt_and_heading_variance():
    quat = np.array([[0.0, 0.0, 0.0, 1.0], [np.nan] * 4])
    variance = rc.orientation_variance_rad2(np.array([2.0, 2.0]), np.array([0.5, 0.5]))
    np.testing.assert_allclose(variance[0], np.radians([0.5, 0.5, 2.0]) ** 2)
    cdr = messages.imu_cdr(np.array([1, 2]), "d", quat, None, None)  # without: unknown, all zeros
    assert not JAZZY.deserialize_cdr(cdr[0], messages.IMU).orientation_covariance.any()
    values = messages.imu_values(quat, None, None, 2, variance)
    given, missing = values[:, 4:13]
    np.testing.assert_allclose(given.reshape(3, 3), np.diag(np.radians([0.5, 0.5, 2.0]) ** 2))
    assert missing[0] == -1.0 and not missing[1:].any()  # an orientation not given stays not given
    assert rc.orientation_variance_rad2(None, None) is None


def test_the_diagnostic_says_the_sigma_and_warns_when_the_heading_is_uncertain():
    calm = rc.device_diagnostic(rc.DeviceState("d", "c1", "ellipsoid", 0.3, heading_sigma_deg=0.8))
    assert calm.level == 0 and dict(calm.values)["heading_sigma_deg"] == "0.8"
    wide = rc.device_diagnostic(rc.DeviceState("d", "c1", "ellipsoid", 0.3, heading_sigma_deg=25.0))
    assert wide.level == 1 and "heading uncertain" in wide.message and "25" in wide.message
    assert rc.UNCERTAIN_HEADING_DEG == 10.0
    assert dict(rc.device_diagnostic(rc.DeviceState("d", "c1")).values)["heading_sigma_deg"] == ""
    assert math.isfinite(float(dict(calm.values)["heading_sigma_deg"]))
