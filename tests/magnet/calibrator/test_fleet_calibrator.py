"""The calibrator's fleet side without Zenoh: rollback restores the earlier coefficients exactly and the history shows
who did it, when and from which id; the fleet answer holds every device with its state, place and open alerts; alert
messages from peers are checked."""

from __future__ import annotations

import numpy as np
import pytest

from magnet import wire
from magnet.calibrator.roster import Roster
from magnet.calibrator.roster_reply import roster_reply
from magnet.drift import Alert, AlertKind, advice_for
from magnet.earth.location import Location
from magnet.fleet.places import Places, parse_places
from magnet.model import Calibration, Quality
from services.calibrator.service import Calibrator, CalibratorSettings
from services.calibrator.store import CalibrationStore


class Clock:
    def __init__(self) -> None:
        self.ns = 1_000_000_000_000

    def __call__(self) -> int:
        self.ns += 1_000_000_000
        return self.ns


def calibration(offset, scale=1.0) -> Calibration:
    matrix = np.diag([scale, 1.0 / scale, 1.0]) + np.array([[0, 0.0123456789, 0], [0.0123456789, 0, 0], [0, 0, 0]])
    return Calibration(
        "ellipsoid",
        np.array(offset, dtype=float) + 1e-9 / 3,
        matrix,
        field_strength=50.123456789,
        quality=Quality(residual_rms_ut=0.31, coverage=0.93),
        accepted=True,
        reason="accepted",
    )


@pytest.fixture
def calibrator(tmp_path):
    with CalibrationStore(tmp_path / "c.db") as store:
        published: list = []
        roster = Roster(
            Places(
                parse_places('{"far": {location: "-33.86,151.21,20", notes: "Sydney"}}'), default=Location(50.45, 30.52)
            )
        )
        yield Calibrator(store, CalibratorSettings(), lambda *a: published.append(a), clock_ns=Clock(), roster=roster)


def test_rollback_restores_the_earlier_coefficients_exactly_and_the_history_shows_it(calibrator):
    first = calibrator.commit("d", calibration([10.0, -20.0, 5.0], 1.1))
    second = calibrator.commit("d", calibration([12.5, -18.0, 4.0], 0.95))
    assert calibrator.records.in_force["d"].id == second.id != first.id
    reply = calibrator.rollback("d", None, "ann@desk")
    assert reply["ok"], reply
    restored = calibrator.records.in_force["d"]
    assert restored.id == first.id
    assert np.array_equal(restored.calibration.offset, first.calibration.offset)
    assert np.array_equal(restored.calibration.matrix, first.calibration.matrix)
    again = calibrator.records.store.latest("d")  # as a restarted calibrator reads it
    assert np.array_equal(again.calibration.offset, first.calibration.offset)
    assert np.array_equal(again.calibration.matrix, first.calibration.matrix)
    rows = calibrator.records.store.history_changes("d")
    assert [r.id for r, _ in rows] == [first.id, second.id, first.id]
    change = rows[0][1]
    assert change["action"] == "rollback" and change["by"] == "ann@desk" and change["from_id"] == second.id
    assert change["to_id"] == first.id and change["at_ns"] == restored.created_ns > second.created_ns
    assert rows[1][1]["action"] == "auto" and rows[1][1]["from_id"] == first.id
    assert rows[2][1]["from_id"] is None
    # to a named id, and refusals that change nothing
    assert calibrator.rollback("d", second.id, "bob")["ok"]
    assert calibrator.records.in_force["d"].id == second.id
    for to, words in [(second.id, "already in force"), ("0123456789abcdef", "no calibration 0123456789abcdef")]:
        reply = calibrator.rollback("d", to, "bob")
        assert not reply["ok"] and words in reply["message"]
    assert not calibrator.rollback("new", None, "bob")["ok"]
    assert len(calibrator.records.store.history("d")) == 4


def test_the_fleet_answer_holds_every_device_its_state_place_and_open_alerts(calibrator):
    calibrator.commit("a", calibration([1.0, 2.0, 3.0]))
    calibrator.roster.seen("a", Location(10.0, 20.0, 30.0), 5)
    calibrator.roster.seen("walker", None, 6)
    alert = Alert("a", AlertKind.FIELD_STRENGTH, 7, 58.0, 50.1, "look for new iron")
    calibrator.roster.on_alert("magnet/a/alert", wire.pack(alert.to_message()), "magnet")
    calibrator.roster.on_alert(
        "magnet/a/alert", wire.pack(Alert("a", AlertKind.DIP, 8, 60, 67, "x").to_message()), "magnet"
    )
    calibrator.roster.on_alert(
        "magnet/a/alert",
        wire.pack({**Alert("a", AlertKind.DIP, 9, 67, 67, "ok").to_message(), "cleared": True}),
        "magnet",
    )
    for bad in [
        b"junk",
        wire.pack({**alert.to_message(), "kind": "vibes"}),
        wire.pack({**alert.to_message(), "measured": float("inf")}),
    ]:
        calibrator.roster.on_alert("magnet/a/alert", bad, "magnet")
    calibrator.roster.on_alert("magnet/b/alert", wire.pack(alert.to_message()), "magnet")  # key of another device
    assert sum(calibrator.roster.drops.counts.values()) == 4
    reply = roster_reply(
        calibrator.records.in_force, calibrator.collections, calibrator.roster, calibrator.state, 10**13
    )
    by = {d["device"]: d for d in reply["devices"]}
    assert reply["count"] == 3 and sorted(by) == ["a", "far", "walker"]
    a = by["a"]
    assert a["state"] == "calibrated" and a["method"] == "ellipsoid" and a["calibration_id"]
    assert a["quality"]["residual_rms_ut"] == 0.31 and a["age_s"] > 0
    assert a["location"] == [10.0, 20.0, 30.0] and a["location_source"] == "reported" and a["last_seen_ns"] == 5
    # the advice shown is magnet's own for the cause, not the sender's words (docs/trust.md)
    assert a["alerts"] == [{**alert.to_message(), "advice": advice_for(AlertKind.FIELD_STRENGTH, 50.1)}]
    assert by["far"]["location_source"] == "fleet" and by["far"]["notes"] == "Sydney"
    assert by["far"]["state"] == "idle" and by["far"]["last_seen_ns"] is None
    assert by["walker"]["location_source"] == "default" and by["walker"]["location"] == [50.45, 30.52, 0.0]


def test_a_device_with_a_place_is_fitted_to_the_model_field_there(calibrator):
    calibrator.roster.seen("a", Location(-33.86, 151.21, 20.0), 1)
    sydney = calibrator.roster.field_ut("a")
    assert sydney == pytest.approx(57.0, abs=1.0)
    assert calibrator.roster.field_ut("unknown") is None
