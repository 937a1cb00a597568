"""The offset from the velocity over the ground (``magnet.calibration.course``; docs/field-calibration.md): a car
that drives straight, whose magnetometer and gyroscope alone identify nothing, gets its heading from its
accelerations against its GNSS velocity and its offset from the WMM's field vector."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from magnet.calibration import FitError
from magnet.calibration.choose import fit_choice
from magnet.calibration.course import course_attitude, earth_vector_ut
from magnet.calibration.field import COURSE_SOURCE, FieldInput, fit_field
from magnet.calibration.fit_input import FitInput
from magnet.calibrator.refresh import gain_pct, velocity_aided
from magnet.simulator import Disturbances, SensorErrors, SimulatorConfig, Trajectory, simulate
from services.bench import field_runs

RATE_HZ = 50.0


@pytest.fixture(scope="module")
def straight_car():
    """The bench's car of seed 2026 (not tuned on): its first 85 s go straight north with speed changes (20 s here)."""
    settings = field_runs.FieldSettings(seconds=20.0)
    run = field_runs.field_run(field_runs.MOTIONS["car"], 2026, settings)
    errors = SensorErrors.phone(np.random.default_rng([2026, 26]), 50.0)
    return run, errors


def _input(run, **changes) -> FieldInput:
    earth = run.earth
    inp = FieldInput(
        run.mag_ut,
        run.acc_ms2,
        run.gyr_rads,
        1.0 / RATE_HZ,
        field_ut=earth.total_ut,
        dip_deg=earth.inclination_deg,
        vel_ned_ms=run.vel_ned_ms,
        declination_deg=earth.declination_deg,
    )
    return dataclasses.replace(inp, **changes)


def test_the_velocity_gives_a_straight_driving_cars_heading_and_tilt(straight_car):
    run, _ = straight_car
    yaw = np.degrees(np.ptp(np.unwrap(np.radians(run.heading_deg))))
    assert yaw < 5.0  # no turn at all
    aligned = course_attitude(run.gyr_rads, run.acc_ms2, 1.0 / RATE_HZ, run.vel_ned_ms)
    assert aligned is not None and aligned.sigma_deg < 1.5
    error = field_runs.heading_error_deg(aligned.quat_wxyz, run.quat_wxyz)
    assert np.sqrt(np.mean(error**2)) < 1.0  # measured: 0.32 deg
    standing = np.zeros_like(run.vel_ned_ms)  # a vehicle that never accelerates says nothing
    assert course_attitude(run.gyr_rads, run.acc_ms2, 1.0 / RATE_HZ, standing) is None


def test_a_straight_driving_car_gets_its_offset_from_the_velocity_and_the_wmm(straight_car):
    run, errors = straight_car
    with pytest.raises(FitError):  # the magnetometer and gyroscope alone identify nothing
        fit_field(_input(run, vel_ned_ms=None))
    record = fit_field(_input(run))
    assert record.accepted and record.method == "offset"
    assert record.quality.get("heading_source") == COURSE_SOURCE and "planar" in record.quality.get("planar")
    assert record.quality.get("course_agreement_deg") < 1.5
    # the heading the record gives, on the run: the calibrated field's horizontal direction against the truth's
    field, truth = record.apply(run.mag_ut), run.true_field_ut
    assert np.linalg.norm(record.offset - errors.hard_iron_ut) < 3.0  # the phone's soft iron at one heading
    angle = np.degrees(np.arctan2(field[:, 1], field[:, 0]) - np.arctan2(truth[:, 1], truth[:, 0]))
    assert np.sqrt(np.mean(((angle + 180.0) % 360.0 - 180.0) ** 2)) < 2.0
    assert velocity_aided(record)
    # a field that changes while the car goes straight (a device moving in the car, iron passing) points away from
    # the WMM's direction: refused. (At one heading the offset takes up any constant error: a declination the WMM
    # has wrong at the place turns the record's heading by as much; the docs say so.)
    swing = 10.0 * np.sin(2 * np.pi * run.t_s / 8.0)[:, None] * np.array([1.0, 0.0, 0.0])
    wrong = fit_field(_input(run, mag=run.mag_ut + swing))
    assert not wrong.accepted and "WMM says" in wrong.reason


def test_a_refresh_from_the_velocity_must_bring_the_field_closer_to_the_wmms_direction(straight_car):
    run, errors = straight_car
    right = errors.true_calibration(run.earth.total_ut)
    kept = fit_field(_input(run, reference=right))
    assert not kept.accepted and "good enough" in kept.reason  # the true calibration is in force
    moved = right.replace(offset=right.offset + np.array([5.0, -6.0, 2.0]))
    refresh = fit_field(_input(run, reference=moved))
    assert refresh.accepted and gain_pct(refresh) is not None and gain_pct(refresh) > 50.0


def test_earth_vector():
    np.testing.assert_allclose(earth_vector_ut(50.0, 90.0, 0.0), [0.0, 0.0, 50.0], atol=1e-12)
    np.testing.assert_allclose(earth_vector_ut(50.0, 0.0, 90.0), [0.0, 50.0, 0.0], atol=1e-12)


def test_a_walker_is_not_calibrated_from_the_velocity():
    """A phone swinging in a hand is not planar: the velocity's heading is not used (no record from it)."""
    errors = SensorErrors.phone(np.random.default_rng(4), 50.0)
    run = simulate(SimulatorConfig(trajectory=Trajectory.WALK_HAND, rate_hz=RATE_HZ, count=1500, errors=errors, seed=4))
    try:
        record = fit_field(_input(run))
    except FitError:
        return
    assert record.quality.get("heading_source") is None


def test_a_car_passing_parked_cars_gets_its_offset_from_the_undisturbed_samples():
    """The bench's car of seed 2026 for 40 s, straight north, past parked cars every 150 m (50 uT at 1 m): the
    magnetometer and gyroscope identify nothing, the velocity's heading does. Its offset is taken from the samples
    outside the parked cars' fields (``magnet.calibration.disturbed``, as every fit): accepted, within 3 uT of the
    hard iron; the same fit with every sample points 4.6 deg from the WMM's field (measured) and is refused."""
    errors = SensorErrors.phone(np.random.default_rng([2026, 26]), 50.0)
    parked = Disturbances(every_m=(150.0, 150.0), first_m=(75.0, 75.0), door_share=0.0, car_m=(1.0, 1.0),
                          car_ut=(50.0, 50.0))  # fmt: skip
    config = SimulatorConfig(
        trajectory=Trajectory.CAR, rate_hz=RATE_HZ, count=int(40 * RATE_HZ), errors=errors, seed=2026,
        disturbances=parked,
    )  # fmt: skip
    run = simulate(config)
    passing = np.linalg.norm(run.disturbance_ut, axis=1) > 1.0
    assert 0.01 < passing.mean() < 0.1  # the car does pass them
    earth = run.earth
    data = FitInput(
        run.mag_ut,
        acc=run.acc_ms2,
        gyr_rads=run.gyr_rads,
        period_s=1.0 / RATE_HZ,
        field_ut=earth.total_ut,
        dip_deg=earth.inclination_deg,
        vel_ned_ms=run.vel_ned_ms,
        declination_deg=earth.declination_deg,
    )
    record = fit_choice(data, "auto")
    assert record.accepted and record.quality.get("heading_source") == COURSE_SOURCE, record.reason
    assert record.quality.get("disturbed_samples", 0) >= passing.sum()
    assert record.quality.get("course_agreement_deg") < 1.5  # measured: 0.82 deg
    assert np.linalg.norm(record.offset - errors.hard_iron_ut) < 3.0  # measured: 1.4 uT
    try:
        every_sample = fit_choice(data.replace(drop_disturbed=False), "auto")
    except FitError:
        return
    assert not every_sample.accepted


def test_a_straight_driving_car_is_ready_to_fit_once_its_velocity_told_the_heading():
    """The calibrator tried a fit from the gyroscope's samples only once the device had turned 90 deg: a car that
    speeds up and slows down on a straight road, whose accelerations against its velocity tell the heading (the
    course fit above), waited for its turns (car of seed 2035: 60 deg by 24 s, its first record at 77 s). It is
    ready once ``MIN_ACCELERATING_S`` of its samples accelerate over the velocity's noise; the same samples without
    the velocity still wait for the turns."""
    from magnet.calibration.collection import Collection
    from magnet.calibration.course import MIN_ACCELERATING_S

    settings = field_runs.FieldSettings(seconds=30.0)
    run = field_runs.field_run(field_runs.MOTIONS["car"], 2026, settings)  # straight north for 85 s
    assert np.degrees(np.ptp(np.unwrap(np.radians(run.heading_deg)))) < 5.0
    t_ns = np.round(run.t_s * 1e9).astype(np.int64)
    aided, plain = Collection("auto", False, 3000), Collection("auto", False, 3000)
    for seq, start in enumerate(range(0, len(t_ns), 25)):
        part = slice(start, start + 25)
        for collection, vel in ((aided, run.vel_ned_ms[part]), (plain, None)):
            collection.add(run.mag_ut[part], run.acc_ms2[part], run.gyr_rads[part], t_ns[part], seq, vel)
    aligned = course_attitude(run.gyr_rads, run.acc_ms2, 1.0 / RATE_HZ, run.vel_ned_ms)
    assert aligned is not None and aligned.accelerating_s >= MIN_ACCELERATING_S  # the heading is told
    assert aided.turn_wait(300) == ""
    assert "turned" in plain.turn_wait(300)
