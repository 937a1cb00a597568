"""Per-device state has a bound: --max-devices on the calibrator and the compass, least recently seen dropped first,
counted; a collection's arrays grow with what it keeps, not with its capacity."""

from __future__ import annotations

import numpy as np
import pytest
from compass_steps import NOW_NS, compass_core

from magnet import wire
from magnet.bounded import Recent
from magnet.calibration.collection import Collection
from magnet.calibrator.roster import Roster
from magnet.drift import Alert, AlertKind
from magnet.earth.expected import Earth
from magnet.earth.location import Location
from magnet.model import Calibration
from services.calibrator.service import Calibrator, CalibratorSettings
from services.calibrator.store import CalibrationStore


def test_recent_forgets_the_least_recently_seen_and_keeps_what_must_stay():
    recent = Recent(2, keep=lambda v: v == "session")
    recent["a"], recent["b"] = "x", "x"
    recent.touch("a")
    recent["c"] = "x"
    assert list(recent) == ["a", "c"] and recent.evicted == 1
    recent["s"] = "session"
    recent["d"] = "x"
    assert "s" in recent and recent.evicted == 3
    with pytest.raises(ValueError, match="a bound must be a whole number"):
        Recent(0)


def _located_batch(device, lat):
    mag = np.random.default_rng(0).normal(size=(10, 3)) * 40
    raw = wire.RawBatch(device, 0, "sim", np.arange(10, dtype=np.int64), mag, None, None, location=Location(lat, 5.0))
    return wire.encode_raw(raw)


def _batch(device, n=10, seed=0):
    mag = np.random.default_rng(seed).normal(size=(n, 3)) * 40
    return wire.encode_raw(wire.RawBatch(device, 0, "sim", np.arange(n, dtype=np.int64), mag, None, None))


def test_calibrator_keeps_at_most_max_devices_collections_and_never_drops_a_session(tmp_path):
    with CalibrationStore(tmp_path / "c.db") as store:
        calibrator = Calibrator(store, CalibratorSettings(max_devices=3), lambda *a: None)
        calibrator.on_raw("magnet/operator-1/raw", _batch("operator-1"), "magnet")  # seen, so a session may start
        assert calibrator.session("operator-1", "start", None)["ok"]
        for i in range(10):
            calibrator.on_raw(f"magnet/flood-{i}/raw", _batch(f"flood-{i}"), "magnet")
        assert len(calibrator.collections) == 3 and "operator-1" in calibrator.collections
        assert calibrator.status("c").to_dict()["evicted_devices"] == 8
        assert len(calibrator.progress_times.last) <= 3


def test_compass_keeps_at_most_max_devices_calibrations():
    compass = compass_core(Earth(), window=3, max_devices=2)
    for i in range(5):
        cal = Calibration("ellipsoid", [float(i), 0, 0], np.eye(3))
        assert compass.accept_calibration(
            wire.encode_calibration(f"d{i}", cal, 1), f"magnet/d{i}/calibration", "magnet"
        )
    assert list(compass.calibrations.in_force) == ["d3", "d4"]
    compass.step(compass.decode([(f"magnet/n{i}/raw", _batch(f"n{i}")) for i in range(5)], "magnet"), NOW_NS)
    # calibrations 3, tails 3, drift trackers 3
    assert len(compass.smoothing.tails) == 2 and compass.status("c").evicted_devices == 3 + 3 + 3


def test_a_collection_that_kept_a_few_samples_holds_small_arrays():
    collection = Collection("ellipsoid", False, 1500)
    collection.add(np.random.default_rng(1).normal(size=(10, 3)) * 40, None)
    assert collection.mag.nbytes <= 64 * 3 * 8
    for seed in range(40):
        collection.add(np.random.default_rng(seed).normal(size=(100, 3)) * 40, None)
    assert 64 < collection.kept <= 1500 and len(collection.mag) >= collection.kept
    assert np.all(np.isfinite(collection.samples()[0]))


def test_a_turntable_session_is_refused_with_what_to_do_instead(tmp_path):
    with CalibrationStore(tmp_path / "c.db") as store:
        calibrator = Calibrator(store, CalibratorSettings(), lambda *a: None)
        reply = calibrator.session("t-1", "start", "turntable")
        assert not reply["ok"] and "magnet fit --method turntable" in reply["message"]
        assert "t-1" not in calibrator.collections


def test_calibrate_with_an_unknown_method_is_one_line_and_asks_nobody(capsys):
    from services.cli import main

    assert (
        main(
            [
                "calibrate",
                "d-1",
                "start",
                "--method",
                "bogus",
                "--timeout",
                "0.1",
                "--no-multicast-scouting",
                "--listen",
                "tcp/127.0.0.1:0",
            ]
        )
        == 2
    )
    err = capsys.readouterr().err
    assert "unknown calibration method 'bogus'" in err and "no calibrator answered" not in err


def test_zenoh_errors_lose_their_rust_source_paths():
    from services.common.zenoh_session import zenoh_message

    raw = (
        "Unable to connect to any of [Single(tls/127.0.0.1:7447)]!  at /root/.cargo/git/checkouts/"
        "zenoh-9c599d5ef3e0480e/cc83980/zenoh/src/net/runtime/orchestrator.rs:447."
    )
    assert zenoh_message(Exception(raw)) == "Unable to connect to any of [Single(tls/127.0.0.1:7447)]!"


def test_a_session_for_a_device_never_seen_is_refused_with_what_to_check(tmp_path):
    with CalibrationStore(tmp_path / "c.db") as store:
        calibrator = Calibrator(store, CalibratorSettings(auto=False), lambda *a: None)
        reply = calibrator.session("ghost-1", "start", None)
        assert not reply["ok"] and "ghost-1 is unknown to this calibrator" in reply["message"]
        assert "ghost-1" not in calibrator.collections and reply["state"] == "idle"
        calibrator.on_raw("magnet/ghost-1/raw", _batch("ghost-1"), "magnet")
        assert calibrator.session("ghost-1", "start", None)["ok"]


def test_the_calibrators_fleet_book_keeps_at_most_max_devices_and_counts_the_rest(tmp_path, caplog):
    with CalibrationStore(tmp_path / "c.db") as store:
        calibrator = Calibrator(store, CalibratorSettings(max_devices=3), lambda *a: None, roster=Roster(max_devices=3))
        book = calibrator.roster
        for i in range(10):
            calibrator.on_raw(f"magnet/flood-{i}/raw", _located_batch(f"flood-{i}", 10.0 + i), "magnet")
            alert = Alert(f"flood-{i}", AlertKind.DIP, i, 60.0, 67.0, "x")
            book.on_alert(f"magnet/flood-{i}/alert", wire.pack(alert.to_message()), "magnet")
            book.seen("known", Location(1.0, 2.0), i)  # a genuine device keeps reporting: it stays
        assert set(book.last_seen_ns) == {"known", "flood-8", "flood-9"}
        assert len(book.places.reported) == 3 and "known" in book.places.reported
        assert set(book.alerts) == {"flood-7", "flood-8", "flood-9"}
        forgotten = calibrator.status("c").to_dict()["forgotten_devices"]
        assert forgotten == book.forgotten == 8 + 8 + 7
        assert len([r for r in caplog.records if "in the roster" in r.getMessage()]) == 1


def _moving_batch(device, lat):
    rng = np.random.default_rng(1)
    n = 10
    raw = wire.RawBatch(
        device,
        0,
        "sim",
        np.arange(n, dtype=np.int64) * 10_000_000 + 1,
        rng.normal(size=(n, 3)) * 40,
        np.tile([0.0, 0.0, -9.81], (n, 1)),
        None,
        np.zeros((n, 3)),
        Location(lat, 5.0),
    )
    return wire.encode_raw(raw)


def test_the_compass_keeps_places_drift_trackers_and_filters_for_at_most_max_devices(caplog):
    compass = compass_core(Earth(), window=1, max_devices=3)
    for i in range(10):
        cal = Calibration("ellipsoid", [float(i), 0, 0], np.eye(3), field_strength=50.0)
        compass.accept_calibration(wire.encode_calibration(f"d{i}", cal, 1), f"magnet/d{i}/calibration", "magnet")
        compass.step(compass.decode([(f"magnet/d{i}/raw", _moving_batch(f"d{i}", 10.0 + i))], "magnet"), NOW_NS)
    assert compass.watch.monitor is not None and list(compass.watch.monitor.trackers) == ["d7", "d8", "d9"]
    assert list(compass.watch.places.reported) == ["d7", "d8", "d9"]
    assert list(compass.filters.devices) == ["d7", "d8", "d9"]
    # calibrations 7, tails 0 (window 1), places 7, trackers 7, filters 7
    assert compass.status("c").evicted_devices == 7 + 7 + 7 + 7
    assert len([r for r in caplog.records if "the least recently seen are forgotten" in r.getMessage()]) == 1


def test_the_compass_remembers_the_keys_of_at_most_twice_max_devices():
    # a flood of new ids once grew the key cache to 200,000 entries (about 60 MB) whatever --max-devices said
    compass = compass_core(Earth(), window=1, max_devices=3)
    for i in range(20):
        compass.step(compass.decode([(f"magnet/f{i}/raw", _batch(f"f{i}"))], "magnet"), NOW_NS)
    assert compass.keys.device("magnet/f19/raw", "magnet") == "f19"
    assert len(compass.keys._devices) == 6


def test_recent_hands_what_it_evicts_to_on_evict_and_get_does_not_touch():
    released: list[tuple[str, int]] = []
    recent: Recent[str, int] = Recent(2, on_evict=lambda key, value: released.append((key, value)))
    recent["a"], recent["b"] = 1, 2
    assert recent.get("a") == 1 and recent.get("zz") is None and recent.get("zz", 0) == 0
    recent["c"] = 3  # "a" was only read, not touched: it is the least recently seen
    assert released == [("a", 1)] and list(recent) == ["b", "c"] and recent.evicted == 1
    recent.clear()
    assert not recent and recent.evicted == 1 and released == [("a", 1)]
