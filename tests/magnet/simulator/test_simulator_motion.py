"""The moving simulator: gyroscope consistent with the attitude, linear acceleration as physics says, errors,
determinism, streaming."""

import numpy as np
import pytest

from magnet import simulator as sim
from magnet.attitude.heading import angle_difference_deg, pitch_roll_deg
from magnet.frames import (
    ned_to_body,
    quaternion_multiply,
    quaternion_to_euler,
    quaternion_to_matrix,
    rotation_angle_deg,
    rotation_vector_to_quaternion,
)

DATE = "2026-03-01"
G = 9.80665
MOVING = sorted(sim.MOVING_TRAJECTORIES, key=lambda t: t.value)


def run(trajectory, count=3000, rate_hz=100.0, **kw):
    return sim.simulate(sim.SimulatorConfig(trajectory=trajectory, count=count, rate_hz=rate_hz, date=DATE, **kw))


def integrate(quat0, gyr_rads, rate_hz):
    """q_k = q_{k-1} exp(gyr_k dt), as a filter integrates: q_k = q_0 exp(gyr_1 dt) ... exp(gyr_k dt), every prefix
    of the product at once (a scan: after the pass of stride d, entry k holds the product of entries k-2d+1..k, in
    order), then normalised."""
    out = rotation_vector_to_quaternion(gyr_rads / rate_hz)
    out[0] = np.asarray(quat0, dtype=float)
    stride = 1
    while stride < len(out):
        out[stride:] = quaternion_multiply(out[:-stride], out[stride:])
        stride *= 2
    return out / np.linalg.norm(out, axis=1, keepdims=True)


def angle_between_deg(qa, qb):
    ra, rb = quaternion_to_matrix(qa), quaternion_to_matrix(qb)
    return rotation_angle_deg(np.einsum("nji,njk->nik", ra, rb))


def test_names_are_the_cli_names_and_still_ones_are_kept():
    assert {t.value for t in sim.Trajectory} >= {
        "spin",
        "turntable",
        "tumble",
        "tenface",
        "multirotor",
        "car",
        "figure8",
        "fast-tumble",
    }
    assert {t.value for t in MOVING} == set(sim.MODELS)
    assert not sim.Trajectory.TUMBLE.moving and sim.Trajectory.CAR.moving


@pytest.mark.parametrize("trajectory", MOVING + [sim.Trajectory.TUMBLE, sim.Trajectory.SPIN])
def test_gyroscope_integrates_to_the_attitude(trajectory):
    r = run(trajectory)
    integrated = integrate(r.quat_wxyz[0], r.true_gyr_rads, 100.0)
    assert angle_between_deg(integrated, r.quat_wxyz).max() < 1e-3
    # the truth angles are those of the quaternion
    yaw, pitch, roll = quaternion_to_euler(r.quat_wxyz)
    ok = np.abs(r.pitch_deg) < 89.0
    assert np.abs(angle_difference_deg(yaw, r.heading_deg))[ok].max() < 1e-6
    np.testing.assert_allclose(pitch, r.pitch_deg, atol=1e-6)
    assert np.abs(angle_difference_deg(roll, r.roll_deg))[ok].max() < 1e-6
    np.testing.assert_allclose(np.linalg.norm(r.quat_wxyz, axis=1), 1.0, atol=1e-12)
    # a smooth trajectory has a rate, not a jump: a sample rotates by less than 10 deg at 100 Hz
    assert np.degrees(np.linalg.norm(r.true_gyr_rads, axis=1)).max() / 100.0 < 10.0


@pytest.mark.parametrize("trajectory", MOVING)
def test_measurements_follow_the_truth_and_the_errors(trajectory):
    e = sim.SensorErrors.random(
        np.random.default_rng(4), 50.0, misalignment_deg=3.0, gyro_bias_rads=(0.01, -0.02, 0.005)
    )
    r = run(trajectory, errors=e, seed=5)
    rotation = quaternion_to_matrix(r.quat_wxyz)
    np.testing.assert_allclose(r.true_field_ut, ned_to_body(rotation, np.array(r.earth.ned_ut)), atol=1e-9)
    np.testing.assert_allclose(r.true_acc_ms2, ned_to_body(rotation, r.lin_acc_ned_ms2 - [0.0, 0.0, G]), atol=1e-9)
    np.testing.assert_allclose(r.acc_ms2, r.true_acc_ms2)
    np.testing.assert_allclose(e.true_calibration().apply(r.mag_ut), r.true_field_ut, atol=1e-9)
    np.testing.assert_allclose(r.gyr_rads - r.true_gyr_rads, np.tile(e.gyro_bias_rads, (len(r.t_s), 1)), atol=1e-12)
    # the device moves: the accelerometer reads more than gravity (a boat's heave and turns, a slow robot's starts,
    # stops and wheels: tenths of m/s^2)
    gentle = trajectory in (sim.Trajectory.BOAT, sim.Trajectory.ROBOT)
    assert np.linalg.norm(r.lin_acc_ned_ms2, axis=1).max() > (0.1 if gentle else 1.0)


def test_gyroscope_noise_and_determinism():
    e = sim.SensorErrors(noise_ut=0.3, acc_noise_ms2=0.05, gyro_noise_rads=0.01, gyro_bias_rads=(0.0, 0.0, 0.02))
    a, b, c = run("car", errors=e, seed=7), run("car", errors=e, seed=7), run("car", errors=e, seed=8)
    for name in ("mag_ut", "acc_ms2", "gyr_rads", "quat_wxyz", "lin_acc_ned_ms2"):
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name))
    assert not np.allclose(a.quat_wxyz, c.quat_wxyz)
    error = a.gyr_rads - a.true_gyr_rads
    np.testing.assert_allclose(error.mean(axis=0), [0.0, 0.0, 0.02], atol=0.001)
    assert np.std(error, axis=0) == pytest.approx([0.01] * 3, rel=0.05)


@pytest.mark.parametrize("trajectory", ["multirotor", "fast-tumble"])
def test_stream_gives_the_run_sample_by_sample_across_blocks(trajectory):
    config = sim.SimulatorConfig(
        trajectory=trajectory,
        count=1500,
        rate_hz=100.0,
        date=DATE,
        seed=2,
        errors=sim.SensorErrors(noise_ut=0.2, gyro_noise_rads=0.01),
    )
    whole = sim.simulate(config)
    stream = sim.SensorStream(config)
    samples = [stream.measure_imu() for _ in range(1500)]
    for i, name in enumerate(("mag_ut", "acc_ms2", "gyr_rads")):
        np.testing.assert_allclose(np.array([s[i] for s in samples]), getattr(whole, name), atol=1e-12)
    np.testing.assert_allclose(stream.last_truth["quat_wxyz"], whole.quat_wxyz[-1], atol=1e-12)
    assert stream.last_truth["heading_deg"] == pytest.approx(whole.heading_deg[-1])
    # a moving run goes on: the next samples are new motion, not a repeat
    mag, _ = stream.measure()
    assert not np.allclose(mag, whole.mag_ut[0], atol=1.0)


def test_multirotor_banks_30_degrees_and_the_accelerometer_sees_it_late():
    r = run("multirotor", count=12000, seed=1)  # two minutes
    rotation = quaternion_to_matrix(r.quat_wxyz)
    tilt = np.degrees(np.arccos(np.clip(rotation[:, 2, 2], -1.0, 1.0)))
    assert 29.0 < tilt.max() < 31.5
    heading = np.unwrap(np.radians(r.heading_deg))
    assert np.ptp(heading) > np.radians(90.0)  # yaw turns
    # thrust along body z: entering a bank the accelerometer still reads level; once drag has settled the speed it
    # sees the tilt (the drag is a force it feels)
    pitch, roll = pitch_roll_deg(r.true_acc_ms2)
    seen = np.hypot(pitch, roll)
    banked = tilt > 25.0
    assert banked.sum() > 200
    assert np.min(seen[banked] / tilt[banked]) < 0.5 and np.max(seen[banked] / tilt[banked]) > 0.8
    speed = np.linalg.norm(np.cumsum(r.lin_acc_ned_ms2[:, :2], axis=0) / 100.0, axis=1)
    assert 5.0 < speed.max() < 16.0  # drag bounds the speed (about 14 m/s at 30 deg)
    # the first samples hover level: about (0, 0, -g) give or take the vibration
    assert np.abs(r.acc_ms2[:100].mean(axis=0) - [0.0, 0.0, -G]).max() < 0.6


def test_car_turns_with_centripetal_acceleration_to_the_inside():
    r = run("car", count=12000, seed=3)
    np.testing.assert_allclose(r.acc_ms2[0], [0.0, 0.0, -G], atol=1e-9)  # parked: level and still
    yaw_rate = r.true_gyr_rads[:, 2]
    right, left = yaw_rate > 0.15, yaw_rate < -0.15
    assert right.sum() > 50 and left.sum() > 50
    assert np.all(r.acc_ms2[right, 1] > 0.5) and np.all(r.acc_ms2[left, 1] < -0.5)
    # lateral acceleration is speed times yaw rate: speed from the longitudinal acceleration integrated
    speed = np.cumsum(np.einsum("nji,nj->ni", quaternion_to_matrix(r.quat_wxyz), r.lin_acc_ned_ms2)[:, 0]) / 100.0
    lateral = np.einsum("nji,nj->ni", quaternion_to_matrix(r.quat_wxyz), r.lin_acc_ned_ms2)[:, 1]
    turning = right | left
    smooth_rate = np.convolve(yaw_rate, np.ones(25) / 25, mode="same")  # the road's jitter averaged out
    np.testing.assert_allclose(lateral[turning], (speed * smooth_rate)[turning], rtol=0.05, atol=0.3)
    assert np.abs(r.pitch_deg).max() < 5.0 and np.abs(r.roll_deg).max() < 6.0


def test_fast_tumble_spins_fast_over_the_whole_sphere():
    r = run("fast-tumble", count=3000, seed=4)
    rate_dps = np.degrees(np.linalg.norm(r.true_gyr_rads, axis=1))
    assert rate_dps.max() > 500.0
    down = -r.true_acc_ms2 / np.linalg.norm(r.true_acc_ms2, axis=1, keepdims=True)
    assert down[:, 2].min() < -0.9 and down[:, 2].max() > 0.9 and np.abs(down[:, 0]).max() > 0.9


def test_figure8_moves_the_hand_and_turns_around():
    r = run("figure8", count=6000, seed=6)
    assert np.ptp(np.unwrap(np.radians(r.heading_deg))) > np.radians(270.0)
    assert np.abs(r.pitch_deg).max() > 35.0 and np.abs(r.roll_deg).max() > 50.0
    lin = np.linalg.norm(r.lin_acc_ned_ms2, axis=1)
    assert 1.0 < lin.max() < 10.0


def test_fleet_gyroscope_integrates_to_each_devices_attitude():
    from magnet.frames import euler_to_quaternion

    fleet = sim.SimulatedDevices(4, rate_hz=100.0, seed=1, date=DATE, gyro=True)
    first, second = fleet.step(60), fleet.step(60)
    gyr = np.concatenate([first.gyr_rads, second.gyr_rads], axis=1)
    quat = euler_to_quaternion(
        *(
            np.concatenate([getattr(first, k), getattr(second, k)], axis=1)
            for k in ("heading_deg", "pitch_deg", "roll_deg")
        )
    )
    for d in range(4):
        assert angle_between_deg(integrate(quat[d, 0], gyr[d], 100.0), quat[d]).max() < 1e-3
    assert sim.SimulatedDevices(4, rate_hz=100.0, seed=1, date=DATE).step(5).gyr_rads is None
