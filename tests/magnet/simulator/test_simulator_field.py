"""The simulator's field motions: walks with their gait, planar vehicles, phone errors, disturbances passed on the
way and a mid-run hard-iron change, each with its truth."""

import numpy as np
import pytest

from magnet import simulator as sim
from magnet.attitude.heading import angle_difference_deg
from magnet.frames import quaternion_to_matrix

DATE = "2026-03-01"
RATE_HZ = 50.0
WALKS = sorted(sim.WALKING_TRAJECTORIES, key=lambda t: t.value)


def run(trajectory, seconds=40.0, seed=3, **kw):
    config = sim.SimulatorConfig(
        trajectory=trajectory, count=int(seconds * RATE_HZ), rate_hz=RATE_HZ, date=DATE, seed=seed, **kw
    )
    return sim.simulate(config)


def tilt_deg(r):
    return np.degrees(np.arccos(np.clip(quaternion_to_matrix(r.quat_wxyz)[:, 2, 2], -1.0, 1.0)))


def dominant_hz(signal, low_hz=0.8):
    """The strongest frequency of a signal above ``low_hz``."""
    spectrum = np.abs(np.fft.rfft(signal - signal.mean()))
    hz = np.fft.rfftfreq(len(signal), 1.0 / RATE_HZ)
    spectrum[hz < low_hz] = 0.0
    return hz[np.argmax(spectrum)]


@pytest.mark.parametrize("trajectory", WALKS)
def test_a_walk_bounces_at_its_step_frequency_and_turns_corners(trajectory):
    r = run(trajectory, seconds=60.0)
    model = sim.MODELS[trajectory.value](np.random.default_rng(0))
    low, high = (2.5, 3.0) if model.PACE == "run" else (1.6, 2.0)
    # the vertical acceleration of the hip and the phone: strongest at the step frequency (or the stride's
    # harmonic, half of it, for a limb that swings)
    vertical = dominant_hz(r.lin_acc_ned_ms2[:, 2])
    assert low - 0.05 <= vertical <= high + 0.05 or low / 2 - 0.05 <= vertical <= high / 2 + 0.05
    # gait: several m/s^2, not tens of g
    magnitude = np.linalg.norm(r.lin_acc_ned_ms2, axis=1)
    assert 1.5 < np.percentile(magnitude, 95) < (40.0 if model.PACE == "run" else 20.0)
    # the walker's course turns corners: headings of the path span more than a right angle
    course = np.unwrap(np.radians(sim.MODELS[trajectory.value].path(model, r.t_s)["course_deg"]))
    assert np.degrees(np.ptp(course)) > 80.0
    # the GNSS-like velocity is a walk's (or a run's)
    speed = np.linalg.norm(np.nanmean(r.vel_ned_ms.reshape(-1, 50, 3), axis=1)[:, :2], axis=1)
    assert 0.8 < np.median(speed) < (4.0 if model.PACE == "run" else 2.0)


def test_texting_is_held_tilted_30_to_45_degrees_and_phoning_stands_the_phone_up():
    texting = tilt_deg(run("walk-texting"))
    assert 25.0 < np.median(texting) < 50.0 and np.ptp(texting) < 25.0
    phoning = tilt_deg(run("walk-phoning"))
    assert np.median(phoning) > 60.0  # its back faces sideways: far from level


def test_seeds_make_different_walks():
    a, b, c = run("walk-pocket", seed=1), run("walk-pocket", seed=1), run("walk-pocket", seed=2)
    np.testing.assert_array_equal(a.quat_wxyz, b.quat_wxyz)
    assert np.abs(angle_difference_deg(a.heading_deg, c.heading_deg)).mean() > 20.0
    assert not np.allclose(a.lin_acc_ned_ms2, c.lin_acc_ned_ms2, atol=0.5)


@pytest.mark.parametrize("trajectory", sorted(sim.PLANAR_TRAJECTORIES, key=lambda t: t.value))
def test_planar_vehicles_only_yaw(trajectory):
    r = run(trajectory, seconds=90.0)
    assert tilt_deg(r).max() < 6.0
    heading = np.unwrap(np.radians(r.heading_deg))
    assert np.degrees(np.ptp(heading)) > 90.0


def test_the_robot_stops_and_turns_in_place():
    r = run("robot", seconds=90.0, seed=4)
    rate = np.degrees(np.linalg.norm(r.true_gyr_rads, axis=1))
    still = (rate < 0.01) & (np.linalg.norm(r.lin_acc_ned_ms2, axis=1) < 0.01)
    assert still.mean() > 0.05  # it stands at times: no rotation, no acceleration, no vibration
    turning_in_place = (rate > 20.0) & (np.linalg.norm(r.lin_acc_ned_ms2, axis=1) < 1.0)
    assert turning_in_place.any()


def test_phone_errors_are_phone_like():
    for seed in range(20):
        e = sim.SensorErrors.phone(np.random.default_rng(seed), 50.0)
        assert 300.0 <= np.linalg.norm(e.hard_iron_ut) <= 750.0
        gains = np.diag(e.soft_iron)
        assert np.all(np.abs(gains - 1.0) <= 0.04)
        off = e.soft_iron - np.diag(gains)
        assert np.abs(off).max() <= 0.015 and np.allclose(off, off.T)
    assert sim.SensorErrors.phone(np.random.default_rng(0), 50.0, noise_ut=0.0).noise_ut == 0.0


def test_objects_passed_on_the_way_change_the_field_for_seconds():
    errors = sim.SensorErrors.phone(np.random.default_rng(1), 50.0, noise_ut=0.0)
    r = run("walk-texting", seconds=120.0, errors=errors, disturbances=sim.Disturbances())
    # the truth: the measured field is the Earth's plus the objects', through the sensor's errors
    field = errors.true_calibration().apply(r.mag_ut)
    np.testing.assert_allclose(field, r.true_field_ut + r.disturbance_ut, atol=1e-9)
    strength = np.linalg.norm(r.disturbance_ut, axis=1)
    assert strength.max() > 5.0
    # each passage lasts seconds, not a sample or a minute
    disturbed = strength > 3.0
    edges = np.flatnonzero(np.diff(disturbed.astype(int)))
    assert len(edges) >= 4  # at least two passages in two minutes (one every 15-40 m at 1.1-1.6 m/s)
    lengths = np.diff(edges)[:: 2 if disturbed[edges[0] + 1] else 1] / RATE_HZ
    assert 0.3 < np.median(lengths) < 10.0
    # direction too, not only magnitude: the field's direction turns while an object is near
    total = r.true_field_ut + r.disturbance_ut
    cosine = np.sum(total * r.true_field_ut, axis=1) / (np.linalg.norm(total, axis=1) * 50.0)
    assert np.degrees(np.arccos(np.clip(cosine[disturbed], -1, 1))).max() > 5.0
    # without disturbances the same walk has none, and the walk itself is the same
    calm = run("walk-texting", seconds=120.0, errors=errors)
    assert not calm.disturbance_ut.any()
    np.testing.assert_array_equal(calm.quat_wxyz, r.quat_wxyz)


def test_disturbances_are_the_same_drawn_at_once_or_streamed():
    config = sim.SimulatorConfig(
        trajectory="walk-hand", count=1500, rate_hz=RATE_HZ, date=DATE, seed=2, disturbances=sim.Disturbances((5, 8))
    )
    whole = sim.simulate(config)
    stream = sim.SensorStream(config)
    mags = np.array([stream.measure_imu()[0] for _ in range(1500)])
    np.testing.assert_allclose(mags, whole.mag_ut, atol=1e-9)
    assert np.linalg.norm(whole.disturbance_ut, axis=1).max() > 1.0


def test_hard_iron_changes_mid_run():
    errors = sim.SensorErrors.phone(np.random.default_rng(2), 50.0, noise_ut=0.0)
    change = sim.HardIronChange(20.0, (100.0, -200.0, 50.0))
    r = run("walk-pocket", errors=errors, hard_iron_change=change)
    after = r.t_s >= 20.0
    np.testing.assert_allclose(r.hard_iron_ut[~after], np.tile(errors.hard_iron_ut, ((~after).sum(), 1)))
    np.testing.assert_allclose(r.hard_iron_ut[after], np.tile([100.0, -200.0, 50.0], (after.sum(), 1)))
    corrected = (r.mag_ut - r.hard_iron_ut) @ np.linalg.inv(errors.distortion).T
    np.testing.assert_allclose(corrected, r.true_field_ut, atol=1e-9)


def test_hard_iron_drifts_with_the_temperature():
    """A phone warming by 0.1 K/s, its hard iron moving by 0.5 uT/K: 2 uT by the end of 40 s, linear in time, and
    the same drift after a change of iron; refused when not three finite numbers."""
    tempco = np.array([0.3, -0.4, 0.0])
    errors = sim.SensorErrors.phone(
        np.random.default_rng(2), 50.0, noise_ut=0.0, temperature_ramp_k_per_s=0.1, hard_iron_tempco_ut_per_k=tempco
    )
    change = sim.HardIronChange(20.0, (100.0, -200.0, 50.0))
    r = run("walk-pocket", errors=errors, hard_iron_change=change)
    before, after = r.t_s < 20.0, r.t_s >= 20.0
    np.testing.assert_allclose(r.hard_iron_ut[before], errors.hard_iron_ut + np.outer(0.1 * r.t_s[before], tempco))
    np.testing.assert_allclose(r.hard_iron_ut[after], [100.0, -200.0, 50.0] + np.outer(0.1 * r.t_s[after], tempco))
    corrected = (r.mag_ut - r.hard_iron_ut) @ np.linalg.inv(errors.distortion).T
    np.testing.assert_allclose(corrected, r.true_field_ut, atol=1e-9)
    with pytest.raises(ValueError, match="hard_iron_tempco_ut_per_k"):
        sim.SensorErrors(hard_iron_tempco_ut_per_k=(1.0, np.nan, 0.0))


def test_gyroscope_bias_drifts_with_the_temperature():
    """A gyroscope's bias moving by 0.03 deg/s per kelvin as the phone warms by 0.1 K/s: 0.12 deg/s by 40 s."""
    tempco = np.radians([0.03, -0.03, 0.02])
    errors = sim.SensorErrors.phone(
        np.random.default_rng(2),
        50.0,
        gyro_noise_rads=0.0,
        temperature_ramp_k_per_s=0.1,
        gyro_bias_tempco_rads_per_k=tempco,
    )
    r = run("walk-pocket", errors=errors)
    np.testing.assert_allclose(r.gyr_rads - r.true_gyr_rads, errors.gyro_bias_rads + np.outer(0.1 * r.t_s, tempco))
    with pytest.raises(ValueError, match="gyro_bias_tempco_rads_per_k"):
        sim.SensorErrors(gyro_bias_tempco_rads_per_k=(0.0, 0.0))


@pytest.mark.parametrize(
    "bad",
    [
        dict(trajectory="tumble", disturbances=sim.Disturbances()),
        dict(trajectory="multirotor", disturbances=sim.Disturbances()),
    ],
)
def test_disturbances_need_a_path(bad):
    with pytest.raises(ValueError, match="along a path"):
        sim.SimulatorConfig(**bad)


@pytest.mark.parametrize(
    "make",
    [
        lambda: sim.Disturbances(every_m=(10.0, 5.0)),
        lambda: sim.Disturbances(door_ut=(-1.0, 5.0)),
        lambda: sim.Disturbances(door_share=2.0),
        lambda: sim.HardIronChange(-1.0, (0.0, 0.0, 0.0)),
        lambda: sim.HardIronChange(1.0, (0.0, 0.0)),
    ],
)
def test_bad_disturbance_settings_are_refused(make):
    with pytest.raises(ValueError):
        make()
