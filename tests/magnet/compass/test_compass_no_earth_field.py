"""With no calibration in force, a raw field no Earth field can be (a phone's hard iron, several times the Earth's
field) never reaches the attitude filter: the heading is the gyroscope's and accelerometer's, flagged disturbed, and
the filter is fed again as soon as a record corrects the field."""

from __future__ import annotations

import numpy as np
import pytest
from compass_steps import compass_core
from fusion_helpers import RATE_HZ, rotating_device
from test_compass_fusion import batches, joined, run_compass

from magnet.attitude import fusion
from magnet.attitude.heading import HeadingFlag, no_earth_field
from magnet.earth.expected import Earth

#: a raw phone magnetometer's hard iron (uT): six times the Earth's field
PHONE_HARD_IRON_UT = np.array([250.0, -40.0, 180.0])


@pytest.fixture(scope="module")
def device():
    return rotating_device(seconds=30.0)


@pytest.mark.parametrize("expected_ut", [None, 49.0])
def test_a_raw_phone_field_leaves_the_filter_on_the_gyroscope(device, expected_ut):
    gyr, acc, mag, _ = device
    raw = (gyr, acc, mag + PHONE_HARD_IRON_UT, None)
    out = run_compass(compass_core(Earth(total_ut=expected_ut), window=1), batches(raw))
    six_axes = fusion.fuse_causal(gyr, acc, None, 1.0 / RATE_HZ)
    np.testing.assert_allclose(joined(out, "heading_deg"), six_axes.heading_deg, atol=1e-6)
    assert np.all(joined(out, "flags") & HeadingFlag.FIELD_DISTURBED)


def test_an_earth_field_still_reaches_the_filter(device):
    gyr, acc, mag, _ = device
    out = run_compass(compass_core(Earth(), window=1), batches(device))
    nine_axes = fusion.fuse_causal(gyr, acc, mag, 1.0 / RATE_HZ)
    np.testing.assert_allclose(joined(out, "heading_deg"), nine_axes.heading_deg, atol=1e-6)


def test_the_band_of_an_earth_field():
    fields = np.array([[0.0, 0.0, 15.0], [30.0, 0.0, 30.0], [0.0, 70.0, 0.0], [300.0, 0.0, 0.0]])
    assert no_earth_field(fields, None).tolist() == [True, False, True, True]  # 22-67 uT anywhere on Earth
    assert no_earth_field(fields, 30.0).tolist() == [True, True, True, True]  # within 30 % of 30 uT: 21-39 uT
    assert no_earth_field(fields, np.array([np.nan, 42.0, 0.0, 50.0])).tolist() == [True, False, True, True]
