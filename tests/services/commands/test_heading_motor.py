"""`magnet heading` applies a record's motor model (the motors' field at the file's current) on both paths, causal
and ``--offline``, through the compass's one correction: a log whose field carries the motors' field gives the
headings of the same log without it."""

from __future__ import annotations

import argparse
import io

import numpy as np
import pytest
from fusion_helpers import RATE_HZ, rotating_device

from magnet.attitude import fusion
from magnet.attitude.heading import HeadingFlag, angle_difference_deg
from magnet.earth.expected import Earth
from magnet.model import Calibration
from magnet.motor import MotorModel
from services.commands import heading
from services.common.inputs.csvio import parse_samples

#: uT per amp, body frame: 20 A adds a 37 uT field, as large as the Earth's
MOTOR_UT_PER_A = np.array([1.5, -1.0, 0.5])


def _table(gyr, acc, mag, current=None):
    columns, names = (
        [(np.arange(len(gyr)) / RATE_HZ)[:, None], mag, acc, gyr],
        ["t_s", "mx,my,mz", "ax,ay,az", "gx,gy,gz"],
    )
    if current is not None:
        columns.append(current[:, None])
        names.append("current_a")
    text = io.StringIO()
    np.savetxt(text, np.hstack(columns), delimiter=",", header=",".join(names), comments="", fmt="%.12g")
    return parse_samples(text.getvalue(), "motor.csv")


@pytest.mark.parametrize("offline", [False, True])
def test_the_motors_field_is_taken_out_on_both_paths(offline: bool):
    gyr, acc, mag, _ = rotating_device(seconds=30.0)
    current = np.linspace(0.0, 20.0, len(gyr))
    with_motors = _table(gyr, acc, mag + current[:, None] * MOTOR_UT_PER_A, current)
    clean = _table(gyr, acc, mag)
    record = Calibration("ellipsoid", np.zeros(3), np.eye(3), motor=MotorModel("current", MOTOR_UT_PER_A))
    plain = Calibration("ellipsoid", np.zeros(3), np.eye(3))
    earth = Earth(0.0, None, None)
    args = argparse.Namespace(rate=None, window=1)

    def headings(table, calibration):
        if offline:
            return heading.offline_headings(table, gyr, calibration, args, earth).headings
        return heading.causal_headings(heading.file_columns(table, gyr, None), calibration, earth, 1, 0).headings

    got, want = headings(with_motors, record), headings(clean, plain)
    np.testing.assert_allclose(got.field_ut, want.field_ut, atol=1e-6)
    assert np.abs(angle_difference_deg(got.heading_deg, want.heading_deg)).max() < 1e-6
    ignored = headings(with_motors, plain)  # the same log without the motor model: degrees off
    assert np.abs(angle_difference_deg(ignored.heading_deg, want.heading_deg)).max() > 2.0


@pytest.mark.parametrize("offline", [False, True])
def test_without_a_record_a_raw_phone_field_is_left_out(offline: bool):
    """No record and a field no Earth field can be (hard iron six times the Earth's): both paths give the heading
    of the gyroscope and accelerometer alone, flagged disturbed (fed to vqf it turned with every tilt)."""
    gyr, acc, mag, _ = rotating_device(seconds=30.0)
    table = _table(gyr, acc, mag + np.array([250.0, -40.0, 180.0]))
    earth = Earth(0.0, 49.0, None)
    if offline:
        got = heading.offline_headings(table, gyr, None, argparse.Namespace(rate=None, window=1), earth).headings
        want = fusion.fuse_offline(gyr, acc, None, 1.0 / RATE_HZ)
    else:
        got = heading.causal_headings(heading.file_columns(table, gyr, None), None, earth, 1, 0).headings
        want = fusion.fuse_causal(gyr, acc, None, 1.0 / RATE_HZ)
    # the file holds 12 digits: vqf's offline pass, forward and back, carries their rounding to a few 0.001 deg
    assert np.abs(angle_difference_deg(got.heading_deg, want.heading_deg)).max() < 0.01
    assert np.all(got.flags & HeadingFlag.FIELD_DISTURBED)
