"""One writer per device among several calibrators, without Zenoh: the lease (who holds it as tokens come and go,
per shard) and what the calibrator does when it stands by or takes over."""

from __future__ import annotations

import numpy as np
import pytest

from magnet import wire
from magnet.model import Calibration
from magnet.shard import Shard
from services.calibrator import queries
from services.calibrator.lease import Lease, Member
from services.calibrator.service import Calibrator, CalibratorSettings
from services.calibrator.store import CalibrationStore

SHARD = Shard(0, 2)
PREFIX = "magnet"


def _token(started_ns, name, shard="0-2"):
    return f"{PREFIX}/@lease/calibrator/{shard}/{started_ns}/{name}"


def test_the_oldest_calibrator_of_the_shard_holds_the_lease():
    lease = Lease(PREFIX, SHARD, Member(200, "b"))
    assert lease.key == _token(200, "b") and lease.active
    assert lease.on_token(_token(300, "c"), True) is None and lease.active  # a later one stands by
    assert lease.on_token(_token(100, "a"), True) is False and not lease.active  # an older one is there
    assert lease.holder == Member(100, "a") and lease.state() == "standby"
    assert lease.on_token(_token(300, "c"), False) is None and not lease.active
    assert lease.on_token(_token(100, "a"), False) is True and lease.active  # its token went away: take over
    assert lease.takeovers == 1


def test_same_start_time_is_ordered_by_name():
    lease = Lease(PREFIX, SHARD, Member(100, "b"))
    assert lease.on_token(_token(100, "a"), True) is False
    assert Lease(PREFIX, SHARD, Member(100, "a")).on_token(_token(100, "b"), True) is None


@pytest.mark.parametrize(
    "key",
    [
        _token(1, "other-shard", shard="1-2"),
        _token(1, "other-count", shard="0-3"),
        f"{PREFIX}/@lease/calibrator/0-2/1",
        f"{PREFIX}/@lease/calibrator/0-2/x/name",
        f"{PREFIX}/@lease/calibrator/0-2/-5/name",
        "other/@lease/calibrator/0-2/1/name",
        f"{PREFIX}/@alive/calibrator/name",
    ],
)
def test_tokens_of_another_shard_or_malformed_ones_change_nothing(key):
    lease = Lease(PREFIX, SHARD, Member(500, "me"))
    assert lease.on_token(key, True) is None and lease.active and lease.members == {Member(500, "me")}


def test_its_own_token_going_away_does_not_make_it_stand_by():
    lease = Lease(PREFIX, SHARD, Member(500, "me"))
    assert lease.on_token(lease.key, False) is None and lease.active


def test_a_name_that_is_not_one_key_chunk_is_refused():
    with pytest.raises(ValueError, match="key chunk"):
        Member(1, "a/b")


def _record(device, created_ns, offset):
    calibration = Calibration("ellipsoid", np.array(offset, float), np.eye(3), 50.0, 300, accepted=True)
    return wire.DeviceCalibration(device, created_ns, calibration)


class Query:
    def __init__(self, key):
        self.key_expr, self.parameters, self.replies = key, {}, []

    def reply(self, key, payload):
        self.replies.append((key, payload))

    def reply_err(self, payload):
        self.replies.append(("err", payload))


def test_a_standby_calibrator_collects_and_answers_nothing_then_takes_over_from_the_store(tmp_path):
    db = tmp_path / "shared.db"
    with CalibrationStore(db) as store, CalibrationStore(db) as other:
        published = []
        calibrator = Calibrator(store, CalibratorSettings(), lambda k, d, p: published.append((k, d)))
        calibrator.stand_by()
        raw = wire.RawBatch("d", 0, "sim", np.arange(3), np.ones((3, 3)), None)
        calibrator.on_raw("magnet/d/raw", wire.encode_raw(raw), PREFIX)
        assert calibrator.status("c").counters.received_batches == 0 and not calibrator.collections
        assert calibrator.status("c").to_dict()["lease"] == "standby"

        other.save(_record("d", 10, [1.0, 2.0, 3.0]))  # the active calibrator stores meanwhile
        query = Query("magnet/d/calibration")
        queries.ANSWERS[wire.Kind.CALIBRATION](query, calibrator, PREFIX)
        assert query.replies == []  # standing by: no answer

        calibrator.take_over()
        assert calibrator.records.in_force["d"].id == other.latest("d").id
        assert published == [(wire.Kind.CALIBRATION, "d")]
        queries.ANSWERS[wire.Kind.CALIBRATION](query, calibrator, PREFIX)
        (answer,) = query.replies
        assert wire.decode_calibration(answer[1]).id == calibrator.records.in_force["d"].id
        status = calibrator.status("c").to_dict()
        assert status["lease"] == "active" and status["takeovers"] == 1


def test_standing_by_ends_the_sessions_in_progress(tmp_path):
    with CalibrationStore(tmp_path / "c.db") as store:
        calibrator = Calibrator(store, CalibratorSettings(auto=False), lambda k, d, p: None)
        raw = wire.RawBatch("d", 0, "sim", np.arange(3), np.ones((3, 3)), None)
        calibrator.on_raw("magnet/d/raw", wire.encode_raw(raw), PREFIX)
        assert calibrator.session("d", "start", None)["ok"]
        calibrator.stand_by()
        assert calibrator.state("d").value == "idle" and not calibrator.collections
