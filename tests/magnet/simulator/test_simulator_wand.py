"""The simulator's hand-held wand (``magnet.simulator.wand``) and a maker-calibrated sensor
(``SensorErrors.calibrated``): slow and fast turns about every axis with rests, the gyroscope integrating to the
attitude, and a field that needs no more than a small correction."""

import numpy as np

from magnet import frames
from magnet import simulator as sim
from magnet.simulator.wand import _axis_angle, _rodrigues

RATE_HZ = 50.0


def wand_run(seed=4, seconds=120.0, **errors):
    config = sim.SimulatorConfig(
        trajectory=sim.Trajectory.WAND,
        count=int(seconds * RATE_HZ),
        rate_hz=RATE_HZ,
        seed=seed,
        errors=sim.SensorErrors(**errors),
    )
    return sim.simulate(config)


def test_the_wand_turns_slowly_and_fast_about_every_axis_and_rests():
    r = wand_run()
    rate_deg_s = np.degrees(np.linalg.norm(r.true_gyr_rads, axis=1))
    assert np.mean(rate_deg_s < 2.0) > 0.03  # rests on the table (no tremor there)
    assert np.mean((rate_deg_s > 10.0) & (rate_deg_s < 90.0)) > 0.1  # slow turns
    assert 200.0 < rate_deg_s.max() < 1000.0  # fast ones
    turning = rate_deg_s > 20.0
    axis_share = np.mean(
        np.abs(r.true_gyr_rads[turning]) / np.linalg.norm(r.true_gyr_rads[turning], axis=1)[:, None], 0
    )
    assert np.all(axis_share > 0.2)  # about x, y and z, not one axis only
    # the field's direction in the body covers much of the sphere (tumbles, upside down)
    down = frames.down_in_body(r.quat_wxyz)
    assert down[:, 2].min() < -0.5 and down[:, 2].max() > 0.9 and np.ptp(down[:, 0]) > 1.2
    # a hand's accelerations: under about 1 g
    assert np.percentile(np.linalg.norm(r.lin_acc_ned_ms2, axis=1), 99) < 10.0


def test_the_wands_gyroscope_integrates_to_its_attitude_and_it_starts_near_level():
    r = wand_run(seed=9, seconds=30.0)
    assert abs(r.pitch_deg[0]) < 6.0 and abs(r.roll_deg[0]) < 6.0
    step = frames.rotation_vector_to_quaternion(r.true_gyr_rads[1:] / RATE_HZ)
    integrated = frames.quaternion_multiply(r.quat_wxyz[:-1], step)
    dot = np.abs(np.sum(frames.w_positive(integrated) * frames.w_positive(r.quat_wxyz[1:]), axis=1))
    assert np.all(dot > 1.0 - 1e-9)


def test_the_same_seed_makes_the_same_wand_and_another_seed_another():
    a, b, c = wand_run(seed=2, seconds=20.0), wand_run(seed=2, seconds=20.0), wand_run(seed=3, seconds=20.0)
    np.testing.assert_array_equal(a.quat_wxyz, b.quat_wxyz)
    assert not np.allclose(a.quat_wxyz, c.quat_wxyz)


def test_axis_angle_gives_back_the_turn():
    rng = np.random.default_rng(0)
    for angle in (0.0, 30.0, 179.9, 180.0):
        axis = rng.standard_normal(3)
        axis /= np.linalg.norm(axis)
        rotation = _rodrigues(axis[None], np.radians([angle]))[0]
        found, found_deg = _axis_angle(rotation)
        np.testing.assert_allclose(_rodrigues(found[None], np.radians([found_deg]))[0], rotation, atol=1e-6)


def test_a_maker_calibrated_sensor_leaves_under_1_ut_and_1_percent():
    for seed in range(20):
        errors = sim.SensorErrors.calibrated(np.random.default_rng(seed), 50.0)
        assert np.linalg.norm(errors.hard_iron_ut) < 1.0
        assert np.max(np.abs(errors.soft_iron - np.eye(3))) <= 0.01
    r = sim.simulate(
        sim.SimulatorConfig(
            trajectory="wand",
            count=3000,
            rate_hz=RATE_HZ,
            errors=sim.SensorErrors.calibrated(np.random.default_rng(1), 50.0),
        )
    )
    # the raw field is the Earth's to within a couple of uT
    assert np.percentile(np.linalg.norm(r.mag_ut - r.true_field_ut, axis=1), 95) < 2.5


def test_a_late_magnetometer_reads_the_field_of_the_attitude_before():
    early, late = wand_run(seed=5, seconds=10.0), wand_run(seed=5, seconds=10.0, mag_lag_s=0.02)
    np.testing.assert_allclose(late.mag_ut[1:], early.true_field_ut[:-1], atol=1e-9)  # one sample at 50 Hz
    np.testing.assert_array_equal(late.true_field_ut, early.true_field_ut)  # the truth is the field now
