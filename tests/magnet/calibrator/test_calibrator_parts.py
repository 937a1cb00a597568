"""Each part of the calibrator through its own public interface, without the composition (``magnet.calibrator.core``)
and without Zenoh: collection, fitting, records, sessions, progress, status, shard keys and the roster's answer."""

from __future__ import annotations

import numpy as np
import pytest

from magnet import wire
from magnet.calibrator.collecting import Collections
from magnet.calibrator.fitting import Fitter
from magnet.calibrator.keys import ShardKeys
from magnet.calibrator.progress import ProgressTimes, progress_of
from magnet.calibrator.records import Records
from magnet.calibrator.roster import Roster
from magnet.calibrator.roster_reply import roster_reply
from magnet.calibrator.sessions import Sessions
from magnet.calibrator.status import State, devices_by_state, state_of
from magnet.earth.location import Location
from magnet.model import Calibration, Quality
from magnet.shard import Shard
from magnet.simulator import SensorErrors, SimulatorConfig, simulate
from services.calibrator.settings import CalibratorSettings
from services.calibrator.store import CalibrationStore

HARD = np.array([30.0, -12.0, 8.0])


def _batch(device: str, n: int = 10, seed: int = 0) -> wire.RawBatch:
    mag = np.random.default_rng(seed).normal(size=(n, 3)) * 40
    return wire.RawBatch(device, 0, "sim", np.arange(n, dtype=np.int64), mag, None, None)


def _sphere_run(count: int = 3000) -> tuple[np.ndarray, np.ndarray]:
    run = simulate(SimulatorConfig(count=count, errors=SensorErrors(hard_iron_ut=HARD, noise_ut=0.3)))
    return run.mag_ut, run.acc_ms2


def _calibration(offset: float) -> Calibration:
    return Calibration(
        "ellipsoid", [offset, 0.0, 0.0], np.eye(3), quality=Quality(residual_rms_ut=0.2, coverage=0.9), accepted=True
    )


@pytest.fixture
def store(tmp_path):
    with CalibrationStore(tmp_path / "c.db") as s:
        yield s


# ---------------------------------------------------------------------------------------------------- collection
def test_collections_open_for_uncalibrated_devices_only_and_count_every_batch():
    collections = Collections(CalibratorSettings())
    assert collections.receive(_batch("new"), calibrated=False) is not None
    assert collections.receive(_batch("done"), calibrated=True) is None
    assert "new" in collections and "done" not in collections and len(collections) == 1
    assert collections.received_batches == 2 and collections.received_samples == 20
    manual = Collections(CalibratorSettings(auto=False))
    assert manual.receive(_batch("new"), calibrated=False) is None and len(manual) == 0


def test_collections_are_bounded_and_a_session_is_never_dropped(caplog):
    collections = Collections(CalibratorSettings(max_devices=2))
    collections.open_session("op", "sphere")
    for i in range(5):
        collections.receive(_batch(f"flood-{i}"), calibrated=False)
    assert list(collections) == ["op", "flood-4"] and collections.evicted == 4
    assert collections.in_session("op") and not collections.in_session("flood-4")
    assert len([r for r in caplog.records if "devices collecting at once" in r.getMessage()]) == 1
    assert collections.clear() == ["op"] and len(collections) == 0


def test_an_automatic_collection_waits_for_coverage_and_says_why_a_session_does_not():
    collections = Collections(CalibratorSettings(min_coverage=0.9))
    spin = simulate(SimulatorConfig(trajectory="spin", count=600, errors=SensorErrors(hard_iron_ut=HARD)))
    batch = wire.RawBatch("d", 0, "sim", np.arange(600), spin.mag_ut, spin.acc_ms2)
    automatic = collections.receive(batch, calibrated=False)
    assert automatic is not None and not collections.ready(automatic, 5.0)
    assert "below 90%" in automatic.last_reason and automatic.last_fit_s == 5.0
    collections.open_session("d", "ellipsoid")
    session = collections.get("d")
    assert session is not None and session is not automatic and collections.ready(session, 5.0)
    collections.end("d")
    assert collections.get("d") is None


# ------------------------------------------------------------------------------------------------------- fitting
def test_the_fitter_scales_to_the_place_else_the_settings_and_counts_each_fit():
    places = {"placed": 57.0}
    fitter = Fitter(CalibratorSettings(field_ut=48.0), places.get)
    assert fitter.field_ut("placed") == 57.0 and fitter.field_ut("elsewhere") == 48.0 and fitter.field_ut(None) == 48.0
    assert Fitter(CalibratorSettings(), places.get).field_ut("elsewhere") is None
    collections = Collections(CalibratorSettings())
    mag, acc = _sphere_run()
    good = collections.receive(wire.RawBatch("d", 0, "sim", np.arange(len(mag)), mag, acc), calibrated=False)
    assert good is not None
    result = fitter.fit(good, 1.0, "d")
    assert result is not None and result.accepted
    np.testing.assert_allclose(result.offset, HARD, atol=1.0)
    few = collections.receive(_batch("few", n=5), calibrated=False)
    assert few is not None and fitter.fit(few, 1.0, "few") is None and few.last_reason
    assert (fitter.fits, fitter.accepted, fitter.rejected) == (2, 1, 1)


def test_a_device_that_reports_no_place_is_fitted_with_the_dip_and_declination_of_the_services_location():
    """``--location`` is the place of the devices that report none: its dip and declination, not only its |B|,
    reach their fits (the ladder's vertical prior; the velocity turned to magnetic north for a vehicle's heading from
    its course). Before, such a device got |B| alone: a car whose hard iron moved 8 uT (tests/magnet/calibrator/
    test_refresh.py) was refreshed by the ladder with the vertical field guessed (heading error of the field 2.2 deg);
    with the place's dip the ladder's offset is not identified from 30 s (its heading noise 1.5-2.7 deg, the true
    horizontal field 0.38 of |B| at a dip of 67.6 deg), and the velocity's course refreshes it: 1.5 deg."""
    from magnet.fleet.places import Places

    here, there = Location.parse("50.45,30.52"), Location.parse("-33.9,18.4")
    roster = Roster(Places(default=here))
    roster.seen("elsewhere", there, 1)
    assert roster.dip_deg("unplaced") == pytest.approx(roster.places.earth("unplaced").inclination_deg)
    assert roster.dip_deg("unplaced") == pytest.approx(67.6, abs=1.0)
    assert roster.declination_deg("unplaced") == pytest.approx(roster.places.earth("unplaced").declination_deg)
    assert roster.dip_deg("elsewhere") < -50.0  # a reported place comes first
    assert Roster().dip_deg("unplaced") is None and Roster().declination_deg("unplaced") is None  # no place at all
    fitter = Fitter(CalibratorSettings(location=here), roster.field_ut, roster.dip_deg, roster.declination_deg)
    assert fitter.dip_at("unplaced") == roster.dip_deg("unplaced")


# ------------------------------------------------------------------------------------------------------- records
def test_records_number_stamp_and_record_each_change_and_read_back_only_their_shard(store):
    records = Records(store, clock_ns=lambda: 7)
    first = records.store_new("d", _calibration(1.0), {"action": "auto", "by": ""})
    second = records.store_new("d", _calibration(2.0), {"action": "session", "by": "ann"})
    assert (first.version, second.version, second.created_ns) == (1, 2, 7)
    assert records.get("d") == second and records.stored == 2
    [(_, change)] = store.history_changes("d", 1)
    assert change == {"action": "session", "by": "ann", "at_ns": 7, "from_id": first.id}
    store.save(wire.DeviceCalibration("other", 9, _calibration(3.0)))  # stored by another calibrator meanwhile
    records.reload()
    assert set(records.in_force) == {"d", "other"}
    owned = {d for d in ("d", "other") if Shard(0, 2).owns(d)}
    assert set(Records(store, shard=Shard(0, 2)).in_force) == owned


# ------------------------------------------------------------------------------------------------------ sessions
class _Host:
    """What a session sees of the rest of the calibrator: which devices are known, their state, and a commit that
    ends the collection (as ``Calibrator.commit`` does)."""

    def __init__(self, collections: Collections) -> None:
        self.collections = collections
        self.committed: list[tuple[str, dict]] = []

    def known(self, device: str) -> bool:
        return device == "seen"

    def state(self, device: str) -> State:
        return state_of(self.collections.get(device), False)

    def commit(self, device: str, calibration: Calibration, change: dict) -> wire.DeviceCalibration:
        self.committed.append((device, change))
        self.collections.end(device)  # as the calibrator does: a stored calibration ends the collection
        return wire.DeviceCalibration(device, 1, calibration, version=1)


def _sessions() -> tuple[Sessions, _Host]:
    collections = Collections(CalibratorSettings(auto=False))
    host = _Host(collections)
    fitter = Fitter(CalibratorSettings(), lambda device: None)
    return Sessions("ellipsoid", collections, fitter, host.known, host.state, host.commit, lambda: 100.0), host


def test_a_session_starts_for_a_known_device_collects_and_commits_with_who_asked():
    sessions, host = _sessions()
    assert not sessions.act("ghost", "start", None)[0]
    assert not sessions.act("seen", "start", "turntable")[0]
    ok, message, _ = sessions.act("seen", "start", "sphere", by="ann@lab")
    assert ok and "sphere" in message and sessions.by == {"seen": "ann@lab"}
    assert sessions.act("seen", "status", None)[1] == "session"
    mag, acc = _sphere_run()
    session = host.collections.get("seen")
    assert session is not None
    session.add(mag, acc)
    ok, _, extra = sessions.act("seen", "commit", None, by="bob@lab")
    assert ok and extra["calibration"]["device"] == "seen"
    assert host.committed == [("seen", {"action": "session", "by": "bob@lab"})]
    assert sessions.by == {}, "nothing kept once no session is open"


def test_a_session_abort_and_the_refusals_change_nothing():
    sessions, host = _sessions()
    assert sessions.act("seen", "abort", None) == (False, "no session to abort", {})
    assert not sessions.act("seen", "commit", None)[0]
    sessions.act("seen", "start", None)
    assert sessions.act("seen", "abort", None)[0] and "seen" not in host.collections
    with pytest.raises(ValueError, match="unknown action 'explode'"):
        sessions.act("seen", "explode", None)
    with pytest.raises(ValueError, match="unknown calibration method"):
        sessions.act("seen", "start", "no-such-method")
    assert host.committed == []


# ------------------------------------------------------------------------------------------- progress and status
def test_progress_says_what_a_collection_waits_for_or_what_is_in_force():
    collections = Collections(CalibratorSettings())
    collection = collections.receive(_batch("d", n=20), calibrated=False)
    waiting = progress_of(State.COLLECTING, 5, collection, None, 150)
    assert waiting.to_dict()["reason"].startswith("20 of 150 evenly spread samples")
    record = wire.DeviceCalibration("d", 1, _calibration(1.0))
    done = progress_of(State.CALIBRATED, 6, None, record, 150).to_dict()
    assert done["state"] == "calibrated" and done["calibration_id"] == record.id and done["accepted"]
    assert progress_of(State.IDLE, 7, None, None, 150).to_dict()["state"] == "idle"


def test_progress_goes_out_at_most_once_an_interval_per_device():
    times = ProgressTimes(max_devices=2, interval_s=0.5)
    assert times.due("d", 0.0)
    times.sent("d", 0.0)
    assert not times.due("d", 0.4) and times.due("d", 0.5) and times.due("e", 0.1)
    for device in "abc":
        times.sent(device, 1.0)
    assert len(times.last) == 2


def test_states_and_their_counts():
    collections = Collections(CalibratorSettings())
    collections.open_session("s", "sphere")
    collections.receive(_batch("c"), calibrated=False)
    states = [state_of(collections.get(d), d == "k") for d in ("s", "c", "k", "i")]
    assert states == [State.SESSION, State.COLLECTING, State.CALIBRATED, State.IDLE]
    assert devices_by_state(states) == {"collecting": 1, "session": 1, "calibrated": 1, "idle": 1}


# ----------------------------------------------------------------------------------------- shard keys and roster
def test_shard_keys_answer_for_their_shard_and_remember_a_bounded_number_of_keys():
    keys = ShardKeys(Shard(0, 2), limit=3)
    devices = [f"dev-{i}" for i in range(10)]
    assert [keys.owns(f"magnet/{d}/raw", "magnet") for d in devices] == [Shard(0, 2).owns(d) for d in devices]
    assert len(keys.owned) == 3 and keys.owned.evicted == 7
    assert keys.owns("not/a/raw/key", "magnet"), "a malformed key goes on, to be refused and counted"
    assert ShardKeys(Shard(0, 1)).owns("anything", "magnet")


def test_the_roster_answer_lists_every_device_it_or_the_records_know():
    roster = Roster()
    roster.seen("walker", Location(1.0, 2.0), 5)
    record = wire.DeviceCalibration("fixed", 10**9, _calibration(1.0))
    reply = roster_reply({"fixed": record}, ["new"], roster, lambda d: State.IDLE, 3 * 10**9)
    by = {entry["device"]: entry for entry in reply["devices"]}
    assert reply["count"] == 3 and list(by) == ["fixed", "new", "walker"]
    assert by["fixed"]["calibration_id"] == record.id and by["fixed"]["age_s"] == 2.0
    assert by["walker"]["last_seen_ns"] == 5 and by["walker"]["location_source"] == "reported"
    assert roster.knows("walker") and not roster.knows("fixed")
