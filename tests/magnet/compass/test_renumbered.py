"""A calibrator that lost its database numbers again from 1 (issue 32 C): a compass holding a higher version must
not refuse every new record as stale while the operator is told "committed". A record numbered below the one held
but made later than any held is applied, said in the log and counted in the status; a replay of an older record,
or of the lost history's high versions, stays refused."""

from __future__ import annotations

import logging

import msgpack
import numpy as np
import pytest
from compass_steps import compass_core

from magnet import signing, wire
from magnet.earth.expected import Earth
from magnet.model import Calibration

KEY = "magnet/k/calibration"
BASE = Calibration("ellipsoid", [10.0, -5.0, 2.0], np.eye(3), field_strength=50, quality={"coverage": 0.9})


@pytest.fixture(scope="module")
def key():
    private_pem, public_pem = signing.new_key_pair()
    return signing.Signer(signing.load_private_key(private_pem)), signing.load_public_key(public_pem)


def _signed(signer, offset_x, created_ns, version):
    calibration = BASE.replace(offset=np.array([offset_x, -5.0, 2.0]))
    record = wire.DeviceCalibration("k", created_ns, calibration, version=version).to_record()
    return msgpack.packb(signer.sign(record))


def test_a_later_record_numbered_again_from_one_is_applied_and_said(key, caplog):
    signer, public = key
    compass = compass_core(Earth(), window=1, trusted=signing.TrustedKeys([public]))
    old_high = _signed(signer, 11.0, 1_000, 6)
    assert compass.accept_calibration(old_high, KEY, "magnet")
    assert compass.accept_calibration(_signed(signer, 12.0, 2_000, 7), KEY, "magnet")
    # the calibrator's database was deleted; restarted on an empty one, the operator's commit is version 1
    commit = _signed(signer, 13.0, 10_000, 1)
    with caplog.at_level(logging.WARNING):
        assert compass.accept_calibration(commit, KEY, "magnet"), compass.drops.counts
    assert compass.calibrations.in_force["k"].version == 1
    assert "history was lost" in caplog.text
    status = compass.status("c")
    assert status.calibrations_renumbered == 1 and status.to_dict()["calibrations_renumbered"] == 1
    assert compass.accept_calibration(_signed(signer, 14.0, 11_000, 2), KEY, "magnet"), "the next one as usual"
    # replays: the lost history's versions 6 and 7 (higher, but made before the numbering started again) and the
    # version 1 just replaced (lower and older) are refused as stale, and nothing changes
    for replay in (old_high, _signed(signer, 12.0, 2_000, 7), commit):
        assert not compass.accept_calibration(replay, KEY, "magnet")
    assert compass.calibrations.in_force["k"].version == 2
    assert compass.drops.counts == {"calibration:stale": 3}


def test_an_older_lower_version_is_still_stale(key):
    signer, public = key
    compass = compass_core(Earth(), window=1, trusted=signing.TrustedKeys([public]))
    assert compass.accept_calibration(_signed(signer, 12.0, 5_000, 7), KEY, "magnet")
    assert not compass.accept_calibration(_signed(signer, 13.0, 4_000, 3), KEY, "magnet")
    assert compass.drops.counts == {"calibration:stale": 1} and compass.status("c").calibrations_renumbered == 0
