"""The services' logic without Zenoh: the calibrator's collection, gate, sessions and store; the compass's maths."""

import json

import numpy as np
import pytest
from compass_steps import compass_core, heading_batches

from magnet import wire
from magnet.attitude.heading import HeadingFlag
from magnet.calibration.collection import Collection, fine_cells
from magnet.earth.expected import Earth
from magnet.model import Calibration
from magnet.simulator import SensorErrors, SimulatorConfig, simulate
from services.calibrator.queries import MAX_HISTORY_LIMIT, history_limit
from services.calibrator.service import Calibrator, CalibratorSettings
from services.calibrator.store import CalibrationStore
from services.commands.heading import load_calibration

HARD = np.array([30.0, -12.0, 8.0])
SOFT = np.array([[1.1, 0.04, 0.0], [0.04, 0.9, 0.02], [0.0, 0.02, 1.0]])


def _run(count=3000, seed=0):
    return simulate(
        SimulatorConfig(count=count, seed=seed, errors=SensorErrors(hard_iron_ut=HARD, soft_iron=SOFT, noise_ut=0.3))
    )


def _feed(calibrator, run, device="d", batch=25):
    for seq, start in enumerate(range(0, len(run.t_s), batch)):
        part = slice(start, start + batch)
        raw = wire.RawBatch(
            device, seq, "sim", np.arange(start, start + len(run.t_s[part])), run.mag_ut[part], run.acc_ms2[part]
        )
        calibrator.on_raw(f"magnet/{device}/raw", wire.encode_raw(raw), "magnet")


class FakeClock:
    def __init__(self):
        self.t = 0.0

    def __call__(self):
        self.t += 0.01
        return self.t


@pytest.fixture
def store(tmp_path):
    with CalibrationStore(tmp_path / "c.db") as s:
        yield s


def _calibrator(store, published, **settings):
    return Calibrator(
        store,
        CalibratorSettings(**settings),
        lambda k, d, p: published.append((k, d, p)),
        clock=FakeClock(),
        clock_ns=lambda: 42,
    )


def test_collection_keeps_one_sample_per_fine_cell_and_stays_bounded():
    collection = Collection("ellipsoid", False, capacity=300)
    run = _run()
    for start in range(0, 3000, 50):
        collection.add(run.mag_ut[start : start + 50], run.acc_ms2[start : start + 50])
    assert collection.seen == 3000 and collection.kept == 300
    mag, acc = collection.samples()
    assert len(np.unique(fine_cells(mag - collection.centre))) >= 260  # evenly spread (the centre moves a little)
    assert acc.shape == (300, 3)


def test_automatic_calibration_is_stored_published_and_then_collection_stops(store):
    published = []
    calibrator = _calibrator(store, published)
    _feed(calibrator, _run())
    record = store.latest("d")
    assert record is not None and record.calibration.accepted
    np.testing.assert_allclose(record.calibration.offset, HARD, atol=1.0)
    assert calibrator.state("d").value == "calibrated" and "d" not in calibrator.collections
    kinds = [k for k, d, p in published]
    assert wire.Kind.CALIBRATION in kinds and wire.Kind.PROGRESS in kinds
    assert wire.decode_calibration(next(p for k, d, p in published if k is wire.Kind.CALIBRATION)).id == record.id
    # a restarted calibrator serves what it stored
    again = _calibrator(store, [])
    assert again.records.in_force["d"].id == record.id and again.state("d").value == "calibrated"


def test_level_spin_is_rejected_with_advice_and_changes_nothing(store):
    published = []
    calibrator = _calibrator(store, published, min_coverage=0.0)
    spin = simulate(
        SimulatorConfig(trajectory="spin", count=2000, errors=SensorErrors(hard_iron_ut=HARD, noise_ut=0.3))
    )
    _feed(calibrator, spin)
    assert store.latest("d") is None
    progress = wire.decode_progress([p for k, d, p in published if k is wire.Kind.PROGRESS][-1])
    assert progress["state"] == "collecting" and progress["coverage"] < 0.5, progress
    assert progress["missing"] and "coverage" in progress["reason"], progress
    assert calibrator.status("c").counters.accepted == 0


def test_session_commit_abort_and_status(store):
    calibrator = _calibrator(store, [], auto=False)
    assert not calibrator.session("d", "commit", None)["ok"]
    _feed(calibrator, _run(count=25))  # the device is seen: a session may start
    started = calibrator.session("d", "start", "sphere")
    assert started["ok"] and started["state"] == "session" and started["progress"]["method"] == "sphere"
    assert calibrator.session("d", "abort", None)["ok"] and calibrator.state("d").value == "idle"
    calibrator.session("d", "start", "ellipsoid", by="ann@lab")
    _feed(calibrator, _run())
    assert store.latest("d") is None, "a session stores only on commit"
    committed = calibrator.session("d", "commit", None, by="bob@lab")
    assert committed["ok"] and committed["calibration"]["id"] == store.latest("d").id
    [(_, change)] = store.history_changes("d", 1)
    assert change["action"] == "session" and change["by"] == "bob@lab"  # who committed it
    assert calibrator.sessions.by == {}  # nothing kept once the session is over
    assert calibrator.session("d", "status", None)["state"] == "calibrated"
    with pytest.raises(ValueError):
        calibrator.session("d", "explode", None)
    with pytest.raises(ValueError):
        calibrator.session("d", "start", "no-such-method")


def test_compass_applies_calibration_tilt_and_declination():
    run = simulate(SimulatorConfig(count=600, errors=SensorErrors(hard_iron_ut=HARD, soft_iron=SOFT)))  # no noise
    truth = SensorErrors(hard_iron_ut=HARD, soft_iron=SOFT).true_calibration()
    compass = compass_core(Earth(declination_deg=7.0), window=1)
    compass.accept_calibration(wire.encode_calibration("d", truth, 1), "magnet/d/calibration", "magnet")
    raw = wire.RawBatch("d", 3, "sim", np.arange(600), run.mag_ut, run.acc_ms2)
    [out] = heading_batches(compass, [raw])
    usable = np.abs(run.pitch_deg) < 85
    error = (out.heading_deg - run.magnetic_heading_deg + 180) % 360 - 180
    assert np.abs(error[usable]).max() < 1e-6
    np.testing.assert_allclose((out.true_heading_deg - out.heading_deg) % 360, 7.0, atol=1e-9)
    np.testing.assert_allclose(out.pitch_deg[usable], run.pitch_deg[usable], atol=1e-6)
    assert np.all(out.flags & HeadingFlag.CALIBRATED) and out.calibration_id == truth.content_id


def test_compass_without_acc_or_calibration_flags_it_and_counts_garbage():
    compass = compass_core(Earth(), window=3)
    raw = wire.RawBatch("x", 0, "sim", np.arange(4), np.tile([20.0, 0.0, 40.0], (4, 1)), None)
    [out] = heading_batches(compass, [raw])
    assert np.all(out.flags & HeadingFlag.NO_TILT) and not np.any(out.flags & HeadingFlag.CALIBRATED)
    np.testing.assert_allclose(out.heading_deg, 0.0, atol=1e-9)
    assert compass.decode([("magnet/x/raw", b"junk"), ("magnet/y/raw", wire.encode_raw(raw))], "magnet").devices == []
    compass.accept_calibration(b"\x93\x01\x02\x03", "magnet/x/calibration", "magnet")
    assert compass.drops.counts == {"raw:not-msgpack": 1, "raw:key-mismatch": 1, "calibration:not-a-map": 1}
    assert compass.calibrations.in_force == {}


def test_compass_identity_when_uncalibrated_matches_raw_field():
    compass = compass_core(Earth(), window=1)
    raw = wire.RawBatch(
        "x",
        0,
        "sim",
        np.arange(2),
        np.array([[10.0, -10.0, 40.0], [0.0, 10.0, 40.0]]),
        np.tile([0.0, 0.0, -9.8], (2, 1)),
    )
    [out] = heading_batches(compass, [raw])
    np.testing.assert_allclose(out.field_ut, raw.mag_ut)
    np.testing.assert_allclose(out.heading_deg, [45.0, 270.0], atol=1e-9)
    np.testing.assert_allclose(out.pitch_deg, 0.0, atol=1e-9)
    assert Calibration  # the record type the compass applies


def test_compass_refuses_an_implausible_calibration_and_keeps_the_one_in_force():
    compass = compass_core(Earth(), window=1)
    genuine = Calibration("ellipsoid", [10.0, 0.0, 0.0], np.eye(3))
    compass.accept_calibration(wire.encode_calibration("k", genuine, 1), "magnet/k/calibration", "magnet")
    for matrix in ([[-1, 0, 0], [0, 1, 0], [0, 0, 1]], np.diag([1e9, 1, 1]).tolist()):
        forged = {**wire.calibration_record("k", genuine, 2), "offset": [100.0, 0, 0], "matrix": matrix}
        compass.accept_calibration(wire.pack(forged), "magnet/k/calibration", "magnet")
    assert compass.calibrations.in_force["k"].id == genuine.content_id
    assert compass.drops.counts == {"calibration:bad-calibration": 2}


def test_heading_command_refuses_an_implausible_calibration_file(tmp_path):
    path = tmp_path / "cal.json"
    good = Calibration("ellipsoid", [1.0, 2.0, 3.0], np.diag([1.0, 1.1, 0.9])).to_dict()
    path.write_text(json.dumps(good))
    assert load_calibration(str(path)).content_id == Calibration.from_dict(good).content_id
    for matrix, words in (
        ([[1, 0, 0], [0, 1, 0], [0, 0, 0]], "condition number"),
        ([[0, 1, 0], [1, 0, 0], [0, 0, 1]], "negative determinant"),
    ):
        path.write_text(json.dumps({**good, "matrix": matrix}))
        with pytest.raises(ValueError, match=f"cal.json: calibration matrix .*{words}"):
            load_calibration(str(path))


def test_history_limit_is_clamped_and_refuses_words():
    assert history_limit(None) == 100 and history_limit("3") == 3 and history_limit("-4") == 0
    assert history_limit("9" * 30) == MAX_HISTORY_LIMIT
    with pytest.raises(ValueError, match="whole number"):
        history_limit("lots")
