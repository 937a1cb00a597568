"""A compass that sees every calibrator go keeps the records in force it holds and says so in its status."""

from __future__ import annotations

import numpy as np

from magnet import wire
from magnet.compass import CompassCore
from magnet.compass.presence import CalibratorPresence
from magnet.model import Calibration


def test_presence_goes_from_unseen_to_present_to_gone_and_back():
    presence = CalibratorPresence()
    assert presence.state == "unseen" and not presence.on_token("m/@alive/calibrator/a", False, 5)
    assert presence.on_token("m/@alive/calibrator/a", True, 10) and presence.state == "present"
    assert not presence.on_token("m/@alive/calibrator/b", True, 11)
    assert not presence.on_token("m/@alive/calibrator/a", False, 20), "one calibrator is still alive"
    assert presence.on_token("m/@alive/calibrator/b", False, 30)
    assert (presence.state, presence.gone_since_ns) == ("gone", 30)
    assert presence.on_token("m/@alive/calibrator/c", True, 40) and presence.gone_since_ns is None


def test_the_records_in_force_stay_when_every_calibrator_is_gone_and_the_status_says_so():
    core = CompassCore()
    record = wire.DeviceCalibration("d", 1, Calibration("ellipsoid", np.array([1.0, 2.0, 3.0]), np.eye(3)), version=1)
    core.on_calibrator("magnet/@alive/calibrator/cal", True, 100)
    core.accept_calibration(wire.pack(record.to_record()), "magnet/d/calibration", "magnet")
    assert core.status("c").calibrations == 1
    core.on_calibrator("magnet/@alive/calibrator/cal", False, 200)
    status = core.status("c").to_dict()
    assert (status["calibrations"], status["calibrators"]) == (1, 0)
    assert (status["calibrators_state"], status["calibrators_gone_since_ns"]) == ("gone", 200)
    assert core.calibrations.in_force["d"].to_record() == record.to_record(), "held exactly as received"
