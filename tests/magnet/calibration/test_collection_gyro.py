"""A collection whose method needs the gyroscope (gyro-ellipsoid): its bounded ring of consecutive samples
(``magnet.calibration.sample_runs``), runs cut at gaps, and a fit from simulator batches that recovers the truth."""

from __future__ import annotations

import numpy as np
import pytest

from magnet import wire
from magnet.calibration.collection import Collection
from magnet.calibration.sample_runs import RecentRuns
from magnet.calibrator.collecting import Collections
from magnet.simulator import SensorErrors, SimulatorConfig, Trajectory, simulate
from services.calibrator.settings import CalibratorSettings

RATE_HZ = 100.0
PERIOD_NS = 10_000_000
BATCH = 25


def _batches(run, start_ns: int = 1_000_000_000):
    """The simulated run as raw batches of BATCH samples, numbered and stamped every PERIOD_NS."""
    t_ns = start_ns + PERIOD_NS * np.arange(len(run.mag_ut), dtype=np.int64)
    for seq, i in enumerate(range(0, len(t_ns), BATCH)):
        part = slice(i, i + BATCH)
        yield wire.RawBatch(
            "dev", seq, "sim", t_ns[part], run.mag_ut[part], run.acc_ms2[part], gyr_rads=run.gyr_rads[part]
        )


@pytest.fixture(scope="module")
def moving():
    """60 s at 100 Hz of a fast tumble, hard iron (12, -7, 4) uT and 5 % soft iron, gyroscope noise and bias."""
    errors = SensorErrors(
        hard_iron_ut=(12.0, -7.0, 4.0),
        soft_iron=((1.05, 0.02, 0.0), (0.02, 0.97, -0.01), (0.0, -0.01, 1.01)),
        noise_ut=0.3,
        gyro_noise_rads=0.002,
        gyro_bias_rads=(0.002, -0.001, 0.001),
    )
    run = simulate(SimulatorConfig(trajectory=Trajectory.FAST_TUMBLE, rate_hz=RATE_HZ, count=6000, errors=errors))
    return run, errors.true_calibration(run.earth.total_ut)


def test_the_calibrator_collection_fits_simulator_batches_with_the_gyroscope_and_finds_the_truth(moving):
    run, truth = moving
    collections = Collections(CalibratorSettings(method="gyro-ellipsoid"))
    fitted = []
    for i, batch in enumerate(_batches(run)):
        collection = collections.receive(batch, calibrated=False)
        assert collection is not None
        now = i * BATCH / RATE_HZ
        if collection.due(150, now) and collections.ready(collection, now):
            fitted.append(collection.fit(run.earth.total_ut, now))
    assert collections.no_gyroscope == 0
    # the first accepted fit is the one the calibrator stores
    first = next(f for f in fitted if f is not None and f.accepted)
    assert first.method == "gyro-ellipsoid"
    np.testing.assert_allclose(first.offset, truth.offset, atol=0.5)  # uT
    last = fitted[-1]
    assert last is not None and last.accepted, last.reason
    np.testing.assert_allclose(last.offset, truth.offset, atol=0.05)
    assert np.abs(last.matrix - truth.matrix).max() < 0.01 * np.abs(truth.matrix).max()
    # fits were tried as the ring grew, not on every batch: a quarter of what it holds must be new
    assert 3 <= len(fitted) <= 25


def test_a_batch_without_the_gyroscope_is_counted_and_explained_not_fitted(moving):
    run, _ = moving
    collections = Collections(CalibratorSettings(method="gyro-ellipsoid"))
    for i, batch in enumerate(_batches(run)):
        collection = collections.receive(
            wire.RawBatch(batch.device, batch.seq, "sim", batch.t_ns, batch.mag_ut, batch.acc_ms2), False
        )
        assert collection is not None and not collection.due(150, i)
    assert collections.no_gyroscope == len(run.mag_ut) // BATCH
    assert "gyro-ellipsoid needs a gyroscope" in collection.last_reason
    assert "needs a gyroscope" in collection.turn_wait(150)


def test_a_level_turn_waits_for_a_turn_about_a_second_axis():
    collection = Collection("gyro-ellipsoid", False, 1000)
    n = 2000  # 20 s turning about z at 1 rad/s, the other axes only noise
    gyr = np.zeros((n, 3))
    gyr[:, 2] = 1.0
    gyr[:, :2] = np.random.default_rng(3).normal(scale=0.01, size=(n, 2))
    t_ns = PERIOD_NS * np.arange(n, dtype=np.int64)
    collection.add(np.ones((n, 3)), None, gyr, t_ns, 0)
    assert "turn the device about every axis" in collection.turn_wait(150)
    gyr[:, 0] = 0.5
    again = Collection("gyro-ellipsoid", False, 1000)
    again.add(np.ones((n, 3)), None, gyr, t_ns, 0)
    assert again.turn_wait(150) == ""


@pytest.mark.parametrize(("turned_deg", "ready"), [(70.0, True), (40.0, False)])
def test_auto_tries_a_level_turn_from_a_sixth_of_a_turn(turned_deg: float, ready: bool):
    """auto's field ladder judges for itself whether a level turn identifies the offset: it is tried from 60 deg
    about one axis (a boat turning slowly for long counts less than its heading moved: on tuning seed 19, 89 deg
    counted by 57.5 s against 108 turned, and 90 made it wait until 77 s)."""
    collection = Collection("auto", False, 1000)
    n = 2000  # 20 s: turning about z at 0.2 rad/s for as long as the turn takes, the other axes only noise
    gyr = np.random.default_rng(3).normal(scale=0.01, size=(n, 3))
    gyr[: int(np.radians(turned_deg) / 0.2 * RATE_HZ), 2] = 0.2
    collection.add(np.ones((n, 3)), None, gyr, PERIOD_NS * np.arange(n, dtype=np.int64), 0)
    assert (collection.turn_wait(150) == "") is ready


def _feed(ring: RecentRuns, t_ns: np.ndarray, seq: int) -> None:
    n = len(t_ns)
    mag = np.column_stack([t_ns, t_ns, t_ns]).astype(float)  # each row names its time
    ring.add(mag, None, np.zeros((n, 3)), t_ns, seq)


def test_the_ring_is_bounded_by_samples_and_keeps_the_newest_in_time_order():
    ring = RecentRuns(capacity=1000)
    assert ring.longest() is None
    for seq in range(100):  # 2,500 consecutive samples through a ring of 1,000
        _feed(ring, PERIOD_NS * (seq * BATCH + np.arange(BATCH, dtype=np.int64)), seq)
    assert ring.held == len(ring.mag) == 1000 and ring.written == 2500
    run = ring.longest()
    assert run is not None and len(run) == 1000
    np.testing.assert_array_equal(run.t_ns, PERIOD_NS * np.arange(1500, 2500))
    np.testing.assert_array_equal(run.mag[:, 0], run.t_ns)  # each sample kept with its own time
    assert run.period_s == pytest.approx(0.01)
    # a device that sent one batch holds a small array, not the capacity's worth
    small = RecentRuns(capacity=30_000)
    _feed(small, PERIOD_NS * np.arange(BATCH, dtype=np.int64), 0)
    assert len(small.mag) < 1000


@pytest.mark.parametrize("cut", ["time", "seq", "backwards"])
def test_a_gap_in_time_or_in_batch_numbers_restarts_the_run(cut):
    ring = RecentRuns(capacity=10_000)
    for seq in range(40):  # 1,000 samples, then the cut, then 500
        _feed(ring, PERIOD_NS * (seq * BATCH + np.arange(BATCH, dtype=np.int64)), seq)
    after = {"time": (1000 + 50, 40), "seq": (1000, 42), "backwards": (500, 40)}[cut]
    for k in range(20):
        start, seq = after[0] + k * BATCH, after[1] + k
        _feed(ring, PERIOD_NS * (start + np.arange(BATCH, dtype=np.int64)), seq)
    run = ring.longest()
    assert run is not None and len(run) == 1000  # the longest: the first, not joined across the cut
    np.testing.assert_array_equal(run.t_ns, PERIOD_NS * np.arange(1000))
    # inside a batch too: a stall (a step of 5 periods: 4 samples missing, more than MOST_MISSING) cuts it
    inside = RecentRuns(capacity=100)
    _feed(inside, PERIOD_NS * np.array([0, 1, 2, 7, 8], dtype=np.int64), 0)
    assert inside.longest() is not None and len(inside.longest()) == 3


def test_a_method_without_the_gyroscope_keeps_no_ring_and_auto_none_before_a_gyroscope_is_seen():
    assert Collection("ellipsoid", False, 100).runs is None
    assert Collection("gyro-ellipsoid", True, 100).runs is not None
    assert Collection("auto", True, 100).runs is None


# ------------------------------------------------------------------------------------------------------------ auto
def test_auto_keeps_the_ring_from_the_first_batch_with_a_gyroscope_and_fits_gyro_ellipsoid_on_it(moving):
    run, truth = moving
    collections = Collections(CalibratorSettings())  # the default: auto
    fitted = []
    for i, batch in enumerate(_batches(run)):
        collection = collections.receive(batch, calibrated=False)
        assert collection is not None and collection.runs is not None
        now = i * BATCH / RATE_HZ
        if collection.due(150, now) and collections.ready(collection, now):
            fitted.append(collection.fit(run.earth.total_ut, now))
    assert collections.no_gyroscope == 0
    last = fitted[-1]
    assert last is not None and last.accepted, last.reason
    assert last.method in ("gyro-ellipsoid", "ellipsoid") and "chosen by auto" in last.reason
    assert last.quality["auto_other"]["method"] != last.method
    np.testing.assert_allclose(last.offset, truth.offset, atol=0.1)


def test_auto_without_a_gyroscope_costs_no_ring_counts_nothing_and_fits_the_ellipsoid_on_the_cells(moving):
    run, truth = moving
    collections = Collections(CalibratorSettings(method="auto"))
    fitted = []
    for i, batch in enumerate(_batches(run)):
        plain = wire.RawBatch(batch.device, batch.seq, "sim", batch.t_ns, batch.mag_ut, None)  # a magnetometer alone
        collection = collections.receive(plain, calibrated=False)
        assert collection is not None and collection.runs is None
        now = i * BATCH / RATE_HZ
        if collection.due(150, now) and collections.ready(collection, now):
            fitted.append(collection.fit(run.earth.total_ut, now))
    assert collections.no_gyroscope == 0 and collection.no_gyroscope == 0
    assert "gyroscope" not in collection.last_reason
    first = next(f for f in fitted if f is not None and f.accepted)
    assert first.method == "ellipsoid" and "auto_other" not in first.quality.extra
    np.testing.assert_allclose(first.offset, truth.offset, atol=1.0)


def test_auto_with_runs_too_short_fits_the_ellipsoid_on_the_cells(moving):
    run, _ = moving
    collection = Collection("auto", True, 1500)
    for k, batch in enumerate(_batches(run)):  # every batch numbered apart: no run longer than a batch
        collection.add(batch.mag_ut, None, batch.gyr_rads, batch.t_ns, 2 * k)
    assert collection.runs is not None and len(collection.runs.longest()) == BATCH
    record = collection.fit(run.earth.total_ut, 1.0)
    assert record is not None and record.method == "ellipsoid" and record.accepted, collection.last_reason
    assert "auto_other" not in record.quality.extra  # the cells hold no rates: the ellipsoid alone


def test_a_session_may_start_with_auto():
    from magnet.calibrator.fitting import Fitter
    from magnet.calibrator.sessions import Sessions

    collections = Collections(CalibratorSettings(auto=False))
    fitter = Fitter(CalibratorSettings(), lambda device: None)
    sessions = Sessions("ellipsoid", collections, fitter, lambda d: True, lambda d: None, None, lambda: 1.0)
    ok, message, _ = sessions.act("dev", "start", "AUTO")
    assert ok and "auto" in message
    session = collections.get("dev")
    assert session is not None and session.method == "auto" and session.runs is None
    with pytest.raises(ValueError, match="auto, minmax2d"):
        sessions.act("dev", "start", "best")


def test_the_ring_keeps_the_velocity_batches_carry_with_their_samples():
    ring = RecentRuns(capacity=100)
    for seq in range(6):  # 150 samples through a ring of 100; the first two batches carry no velocity
        t_ns = PERIOD_NS * (seq * BATCH + np.arange(BATCH, dtype=np.int64))
        vel = None if seq < 2 else np.column_stack([t_ns, -t_ns, 0 * t_ns]).astype(float)
        ring.add(np.ones((BATCH, 3)), None, np.zeros((BATCH, 3)), t_ns, seq, vel)
    run = ring.longest()
    assert run is not None and run.vel_ned_ms is not None and len(run.vel_ned_ms) == 100
    known = np.isfinite(run.vel_ned_ms).all(axis=1)
    np.testing.assert_array_equal(known, run.t_ns >= PERIOD_NS * 2 * BATCH)
    np.testing.assert_array_equal(run.vel_ned_ms[known, 0], run.t_ns[known])
    assert run.tail(0.2).vel_ned_ms is not None and len(run.tail(0.2).vel_ned_ms) == 20
    plain = RecentRuns(capacity=100)
    _feed(plain, PERIOD_NS * np.arange(BATCH, dtype=np.int64), 0)
    assert plain.longest() is not None and plain.longest().vel_ned_ms is None  # no velocity: none
