"""In-service recalibration (``magnet.calibrator.refresh``, ``--recalibrate``): a calibrated phone whose hard iron
changed is refreshed from its normal use (a walk while texting) against the record in force; propose opens a session
instead; off leaves the record alone; a record that is still right is not replaced."""

from __future__ import annotations

import dataclasses
import itertools

import numpy as np
import pytest
from memory_store import MemoryStore

from magnet import wire
from magnet.calibrator import CalibratorCore, refresh
from magnet.calibrator.refresh import Refresher
from magnet.calibrator.status import State
from magnet.earth.location import Location
from magnet.frames import quaternion_to_matrix
from magnet.model import Quality
from magnet.quality.motion import AIDED_SOURCE
from magnet.shard import Shard
from magnet.simulator import SensorErrors, SimulatorConfig, Trajectory, simulate
from services.calibrator.settings import CalibratorSettings

RATE_HZ = 100.0
NOW_NS = 1_700_000_000_000_000_000
SECONDS = 50.0


class DataClock:
    """The monotonic clock follows the samples fed (s); the wall clock stands still."""

    def __init__(self) -> None:
        self.t_s = 0.0

    def monotonic(self) -> float:
        return self.t_s

    def wall_ns(self) -> int:
        return NOW_NS


@pytest.fixture(scope="module")
def walk():
    """A texting walk of a phone whose hard iron is 8 times the field, and the same phone before its hard iron
    moved by 6 uT (a magnet in a new case): the record in force is the old one."""
    rng = np.random.default_rng(5)
    errors = SensorErrors.phone(rng, 50.0)
    run = simulate(
        SimulatorConfig(
            trajectory=Trajectory.WALK_TEXTING,
            rate_hz=RATE_HZ,
            count=int(SECONDS * RATE_HZ),
            errors=errors,
            seed=11,
            lat_deg=50.45,
            lon_deg=30.52,
        )
    )
    old = errors.true_calibration(run.earth.total_ut)
    old = old.replace(offset=old.offset - np.array([6.0, -4.0, 3.0]))
    return run, old


def _core(clock: DataClock, store: MemoryStore, recalibrate: str) -> CalibratorCore:
    settings = CalibratorSettings(recalibrate=recalibrate, location=None)
    return CalibratorCore(store, settings, lambda *a: None, clock.monotonic, clock.wall_ns, None, shard=Shard(0, 1))


def _feed(core: CalibratorCore, clock: DataClock, run, batch: int = 50, speed_ms: float | None = None) -> None:
    """The run in raw batches; with ``speed_ms`` each batch also carries a velocity of that speed, north."""
    for seq, start in enumerate(range(0, len(run.t_s), batch)):
        part = slice(start, start + batch)
        t_ns = np.round(run.t_s[part] * 1e9).astype(np.int64)
        vel = None if speed_ms is None else np.tile([speed_ms, 0.0, 0.0], (len(t_ns), 1))
        raw = wire.RawBatch(
            "d", seq, "sim", t_ns, run.mag_ut[part], run.acc_ms2[part], gyr_rads=run.gyr_rads[part], vel_ned_ms=vel
        )
        clock.t_s = float(run.t_s[part][-1])
        core.on_raw("magnet/d/raw", wire.encode_raw(raw), "magnet")


def _direction_error_deg(calibration, run) -> float:
    """RMS (deg) of the heading error the calibrated field makes: the angle between its horizontal part and the true
    field's, both turned into the Earth frame by the true attitude."""
    rotation = quaternion_to_matrix(run.quat_wxyz)
    field = np.einsum("nij,nj->ni", rotation, calibration.apply(run.mag_ut))
    truth = np.einsum("nij,nj->ni", rotation, run.true_field_ut)
    error = np.arctan2(field[:, 1], field[:, 0]) - np.arctan2(truth[:, 1], truth[:, 0])
    return float(np.degrees(np.sqrt(np.mean(np.angle(np.exp(1j * error)) ** 2))))


def _calibrated(recalibrate: str, in_force) -> tuple[CalibratorCore, MemoryStore, DataClock]:
    store, clock = MemoryStore(), DataClock()
    core = _core(clock, store, recalibrate)
    core.commit("d", in_force, {"action": "manual", "by": "test"})
    return core, store, clock


def test_a_changed_hard_iron_is_refreshed_in_service_and_history_says_so(walk):
    run, old = walk
    core, store, clock = _calibrated("auto", old)
    _feed(core, clock, run)
    changes = [change for _, change in store.history_changes("d")]
    assert changes[-1]["action"] == "manual"  # newest first
    refreshes = [c for c in changes if c["action"] == "refresh"]
    assert refreshes and all(c["in_service"] for c in refreshes)
    assert refreshes[0]["gain_pct"] >= 15.0
    assert core.status("c").counters.refreshed == len(refreshes) >= 1
    now = core.records.get("d")
    assert now is not None and now.version == 1 + len(refreshes)
    assert _direction_error_deg(now.calibration, run) < _direction_error_deg(old, run) / 2
    assert core.state("d") is State.CALIBRATED  # refreshing does not change what the device's state says


def test_propose_opens_a_session_holding_the_refresh_and_off_leaves_the_record(walk):
    run, old = walk
    core, store, clock = _calibrated("propose", old)
    _feed(core, clock, run)
    assert len(store.history_changes("d")) == 1 and core.state("d") is State.SESSION
    assert core.status("c").counters.proposed == 1
    core, store, clock = _calibrated("off", old)
    _feed(core, clock, run)
    assert len(store.history_changes("d")) == 1 and core.state("d") is State.CALIBRATED
    assert core.status("c").counters.refresh_fits == 0


def test_a_record_that_is_still_right_is_not_replaced(walk):
    run, old = walk
    right = old.replace(offset=old.offset + np.array([6.0, -4.0, 3.0]))
    core, store, clock = _calibrated("auto", right)
    _feed(core, clock, run)
    assert len(store.history_changes("d")) == 1
    assert core.status("c").counters.refresh_fits >= 1


def test_a_travelling_device_gets_a_refresh_judged_without_its_velocity_proposed_not_committed(walk):
    """A vehicle's linear accelerations can fool a judgement whose attitude has no velocity aiding: measured through
    the services, a car's refresh judged so turned its heading 118 deg wrong. A travelling device's (velocity over
    5 m/s) refresh is committed only when the field ladder judged it with the velocity-aided attitude (quality
    dip_source); any other is proposed as a session, and the record in force stays."""
    run, old = walk
    refresher = Refresher("auto", 2000, 4)
    collection = refresher.receive(_raw(run, 0, 50, speed_ms=8.0))
    assert collection is not None and collection.travelled
    unaided = old.replace(quality=Quality().with_extra(dip_source="fused gravity"))
    aided = old.replace(quality=Quality().with_extra(dip_source=AIDED_SOURCE))
    assert refresher.proposes(collection, unaided) and refresher.proposes(collection, None)
    assert not refresher.proposes(collection, aided)
    assert Refresher("propose", 2000, 4).proposes(collection, aided)  # propose: always a session
    walker = Refresher("auto", 2000, 4).receive(_raw(run, 0, 50, speed_ms=1.4))  # a walker's GNSS speed
    assert walker is not None and not walker.travelled
    core, _, clock = _calibrated("auto", old)
    _feed(core, clock, run, speed_ms=1.4)
    assert core.status("c").counters.refreshed >= 1


def test_a_car_whose_hard_iron_moved_is_refreshed_in_service_judged_with_its_velocity():
    """A car (GNSS velocity in its batches, 60 s of town driving) whose record in force misses a hard-iron change of
    8 uT: the field ladder judges the refresh with the velocity-aided attitude, so ``auto`` commits it, and it
    brings the calibrated field's heading error down (11.4 -> 2.2 deg RMS against the truth)."""
    errors = SensorErrors.phone(np.random.default_rng(16), 50.0)
    run = simulate(
        SimulatorConfig(
            trajectory=Trajectory.CAR, rate_hz=50.0, count=3000, errors=errors, seed=16, lat_deg=50.45, lon_deg=30.52
        )
    )
    old = errors.true_calibration(run.earth.total_ut)
    old = old.replace(offset=old.offset - np.array([6.0, -4.0, 3.0]))
    store, clock = MemoryStore(), DataClock()
    settings = CalibratorSettings(location=Location.parse("50.45,30.52"))
    core = CalibratorCore(store, settings, lambda *a: None, clock.monotonic, clock.wall_ns, None, shard=Shard(0, 1))
    core.commit("d", old, {"action": "manual", "by": "test"})
    for seq, start in enumerate(range(0, len(run.t_s), 25)):
        part = slice(start, start + 25)
        raw = wire.RawBatch(
            "d",
            seq,
            "sim",
            np.round(run.t_s[part] * 1e9).astype(np.int64),
            run.mag_ut[part],
            run.acc_ms2[part],
            gyr_rads=run.gyr_rads[part],
            vel_ned_ms=run.vel_ned_ms[part],
        )
        clock.t_s = float(run.t_s[part][-1])
        core.on_raw("magnet/d/raw", wire.encode_raw(raw), "magnet")
    counters = core.status("c").counters
    assert counters.refreshed >= 1 and counters.proposed == 0
    now = core.records.get("d")
    assert now is not None and now.calibration.quality.get("dip_source") == AIDED_SOURCE
    assert _direction_error_deg(now.calibration, run) < _direction_error_deg(old, run) / 3


def _raw(run, seq: int, batch: int, speed_ms: float) -> wire.RawBatch:
    part = slice(seq * batch, (seq + 1) * batch)
    return wire.RawBatch(
        "d",
        seq,
        "sim",
        np.round(run.t_s[part] * 1e9).astype(np.int64),
        run.mag_ut[part],
        run.acc_ms2[part],
        gyr_rads=run.gyr_rads[part],
        vel_ned_ms=np.tile([speed_ms, 0.0, 0.0], (batch, 1)),
    )


def test_after_the_iron_changes_the_old_samples_go_and_a_refresh_is_tried_sooner_and_more_often(walk):
    """The record in force misses the field strength for CHANGED_S (four batches of 0.5 s): what came before is
    dropped and, the record being known wrong, a refresh is tried from CHANGED_MIN_S of samples on, every
    CHANGED_INTERVAL_S."""
    run, old = walk
    right = old.replace(offset=old.offset + np.array([6.0, -4.0, 3.0]))
    refresher = Refresher("auto", 2000, 4)
    shift = np.array([80.0, -60.0, 40.0])  # a magnet in the new case: the field strength is far off
    first = None
    for seq in range(40):  # 10 s as it was, then the new iron
        batch = _raw(run, seq, 50, speed_ms=0.0)
        if seq >= 20:
            batch = dataclasses.replace(batch, mag_ut=batch.mag_ut + shift)
        collection = refresher.receive(batch, right)
        first = first or collection
        assert collection is not None
        if seq < 20 + refresh.CHANGED_BATCHES - 1:
            assert collection is first and not collection.after_change
    assert collection is not first and collection.after_change
    assert collection.runs is not None and collection.runs.written <= 20 * 50  # only what came after the change
    now = 100.0
    due = []
    for seq in range(40, 60):
        batch = dataclasses.replace(_raw(run, seq, 50, speed_ms=0.0), mag_ut=_raw(run, seq, 50, 0.0).mag_ut + shift)
        refresher.receive(batch, right)
        now += 10.0
        due.append(refresher.due(collection, now))
    # the collection holds 9 s after the change at the first look (batches 23-40): due at once, under the 12 s an
    # ordinary refresh waits for; then every 3 s of samples
    assert refresh.CHANGED_MIN_S < 9.0 < refresh.REFRESH_MIN_S and due[0]
    times = [(40 + k + 1) * 0.5 for k, d in enumerate(due) if d]  # seconds of the walk when a refresh was due
    assert len(times) >= 3
    assert all(b - a == pytest.approx(refresh.CHANGED_INTERVAL_S) for a, b in itertools.pairwise(times))


def test_the_iron_changed_is_judged_in_seconds_not_batches(walk):
    """In ``magnet edge``'s batches of 10 samples at 200 Hz (here 5 at 100 Hz: 0.05 s) a field strength missed for
    1 s (a door passed) is no new iron: the collection is kept; missed for CHANGED_S it is. Counted as 4 batches, the
    iron had changed after 0.2 s."""
    run, old = walk
    right = old.replace(offset=old.offset + np.array([6.0, -4.0, 3.0]))
    refresher = Refresher("auto", 2000, 4)
    shift = np.array([80.0, -60.0, 40.0])
    first = None
    for seq in range(400):  # 10 s as it was, then 1 s off, 5 s as it was, then off for good
        batch = _raw(run, seq, 5, speed_ms=0.0)
        off = 200 <= seq < 220 or seq >= 320
        if off:
            batch = dataclasses.replace(batch, mag_ut=batch.mag_ut + shift)
        collection = refresher.receive(batch, right)
        first = first or collection
        assert collection is not None
        if seq < 320 + round(refresh.CHANGED_S / 0.05) - 1:
            assert collection is first and not collection.after_change, seq
    assert collection is not first and collection.after_change
