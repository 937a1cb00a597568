"""magnet.quality.disturbance: the samples of a field that a passing object disturbs, found by |B|, dip and steps the
rotation does not explain, against the simulator's truth."""

import numpy as np
import pytest

from magnet import simulator as sim
from magnet.quality.disturbance import DisturbanceSettings, field_disturbance, integrated_attitude

RATE_HZ = 50.0


def walk(trajectory="walk-texting", seconds=60.0, seed=1, disturbances=True):
    errors = sim.SensorErrors.phone(np.random.default_rng(seed), 50.0)
    run = sim.simulate(
        sim.SimulatorConfig(
            trajectory=trajectory,
            rate_hz=RATE_HZ,
            count=int(seconds * RATE_HZ),
            seed=seed,
            errors=errors,
            disturbances=sim.Disturbances() if disturbances else None,
        )
    )
    return run, errors.true_calibration().apply(run.mag_ut)


def judge(run, field, **kw):
    return field_disturbance(
        field,
        acc_ms2=run.acc_ms2,
        gyr_rads=run.gyr_rads,
        period_s=1.0 / RATE_HZ,
        expected_ut=run.earth.total_ut,
        expected_dip_deg=run.earth.inclination_deg,
        **kw,
    )


@pytest.mark.parametrize("trajectory", ["walk-texting", "walk-hand", "robot"])
def test_every_strongly_disturbed_sample_is_flagged_and_a_calm_walk_mostly_is_not(trajectory):
    run, field = walk(trajectory, seed=1)
    flags = judge(run, field)
    strength = np.linalg.norm(run.disturbance_ut, axis=1)
    if (strength > 2.0).any():
        assert flags.disturbed[strength > 2.0].all()
    calm_run, calm_field = walk(trajectory, seed=1, disturbances=False)
    calm = judge(calm_run, calm_field)
    assert calm.disturbed.mean() < 0.15
    assert not calm.step.any() and not calm.magnitude.any()


def test_a_horizontal_turn_of_the_field_is_caught_by_the_steps_alone():
    """A disturbance that turns the field in the horizontal plane without changing |B| or dip: only the
    rotation-compensated step sees it (and it is the one that turns the heading)."""
    run, field = walk("walk-pocket", seconds=40.0, disturbances=False)
    rotation = np.zeros(len(field))
    rotation[1000:1200] = np.radians(15.0) * np.sin(np.linspace(0.0, np.pi, 200))  # 4 s, up to 15 deg
    down = np.einsum("nji,j->ni", sim_rotation(run), [0.0, 0.0, 1.0])  # NED down in body axes
    turned = np.array([rotate_about(f, d, a) for f, d, a in zip(field, down, rotation)])
    flags = judge(run, turned)
    assert not flags.magnitude[1000:1200].any() and not flags.dip[1000:1200].any()
    assert flags.step[1000:1200].mean() > 0.5 and flags.disturbed[1050:1150].all()
    assert not flags.disturbed[:800].any()  # before it: its 2 s window and 1 s hold


def sim_rotation(run):
    from magnet.frames import quaternion_to_matrix

    return quaternion_to_matrix(run.quat_wxyz)


def rotate_about(vector, axis, angle):
    axis = axis / np.linalg.norm(axis)
    return (
        vector * np.cos(angle) + np.cross(axis, vector) * np.sin(angle) + axis * (axis @ vector) * (1 - np.cos(angle))
    )


def test_without_gyroscope_or_expectation_the_medians_are_the_reference():
    run, field = walk(seconds=60.0)
    flags = field_disturbance(field, acc_ms2=run.acc_ms2)
    assert flags.expected_ut == pytest.approx(run.earth.total_ut, rel=0.02)
    strength = np.linalg.norm(run.disturbance_ut, axis=1)
    assert flags.disturbed[strength > 10.0].all()  # |B| and the norm's steps still see the strong ones
    only_field = field_disturbance(field)
    assert np.isnan(only_field.dip_deg).all() and not only_field.dip.any()


def test_integrated_attitude_is_the_product_of_the_steps():
    rates = np.random.default_rng(0).normal(0.0, 2.0, (37, 3))
    quat = integrated_attitude(rates, 0.02)
    from magnet.frames import quaternion_multiply, rotation_vector_to_quaternion

    expected = np.array([1.0, 0.0, 0.0, 0.0])
    for k, step in enumerate(rotation_vector_to_quaternion(rates * 0.02)):
        expected = quaternion_multiply(expected, step)
        assert np.allclose(quat[k], expected) or np.allclose(quat[k], -expected)


@pytest.mark.parametrize(
    "bad",
    [dict(field_tol_pct=-1.0), dict(steps=((0.25,),)), dict(hold_s=float("nan"))],
)
def test_bad_settings_are_refused(bad):
    with pytest.raises(ValueError):
        DisturbanceSettings(**bad)


def test_bad_input_is_refused():
    with pytest.raises(ValueError, match="shape"):
        field_disturbance(np.zeros((5, 2)))
    with pytest.raises(ValueError, match="period_s"):
        field_disturbance(np.ones((5, 3)), gyr_rads=np.zeros((5, 3)))
