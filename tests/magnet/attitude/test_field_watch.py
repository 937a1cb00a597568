"""magnet.attitude.field_watch: the compass's causal watch over the field, and the filter that leans on the gyroscope
while the field is disturbed (magnet.attitude.fusion), against the simulator's truth."""

import numpy as np
import vqf

from magnet import frames
from magnet.attitude import fusion
from magnet.attitude.field_watch import FieldWatch
from services.bench import field_runs

PERIOD_S = 0.02


def walk(name="walk-texting", seconds=40.0, seed=1):
    run = field_runs.field_run(field_runs.MOTIONS[name], seed, field_runs.FieldSettings(seconds=seconds))
    return run, run.errors.true_calibration().apply(run.mag_ut)


def turned_field(run, field, start, stop, degrees):
    """The field turned about the vertical by up to ``degrees`` (a sine squared) from sample start to stop: a
    disturbance that keeps |B| and dip, which only the rotation-compensated steps can see."""
    down = frames.quaternion_to_matrix(run.quat_wxyz)[:, 2, :]
    angle = np.zeros(len(field))
    angle[start:stop] = np.radians(degrees) * np.sin(np.linspace(0.0, np.pi, stop - start)) ** 2
    c, s = np.cos(angle)[:, None], np.sin(angle)[:, None]
    along = np.sum(down * field, axis=1, keepdims=True) * down
    return field * c + np.cross(down, field) * s + along * (1.0 - c)


def watch_flags(field, gyr, batch):
    watch = FieldWatch(PERIOD_S)
    return np.concatenate([watch.update(field[i : i + batch], gyr[i : i + batch]) for i in range(0, len(field), batch)])


def test_the_flags_do_not_depend_on_how_the_samples_are_batched():
    run, field = walk(seconds=30.0)
    field = turned_field(run, field, 800, 1050, 30.0)
    whole = watch_flags(field, run.gyr_rads, len(field))
    np.testing.assert_array_equal(watch_flags(field, run.gyr_rads, 7), whole)
    np.testing.assert_array_equal(watch_flags(field, run.gyr_rads, 25), whole)
    assert whole[900:1000].any()


def test_a_calm_walk_is_not_flagged_even_with_an_imperfect_calibration():
    run, field = walk("walk-hand")
    assert not watch_flags(field, run.gyr_rads, 25).any()
    sphere = field_runs.sphere_fit_field(run.mag_ut)  # no soft iron: |B| wobbles with the attitude
    assert watch_flags(sphere, run.gyr_rads, 25).mean() < 0.02


def test_a_field_that_stays_changed_becomes_the_new_normal():
    run, field = walk(seconds=45.0)
    field = field.copy()
    field[1000:] += np.array([15.0, -10.0, 5.0])  # a magnet fixed to the device: a calibration no longer right
    flags = watch_flags(field, run.gyr_rads, 25)
    assert flags[1000:1100].any()
    assert not flags[1000 + int(20.0 / PERIOD_S) :].any()  # learnt again within 20 s (measured: 13.6 s)


def test_the_filter_holds_its_heading_on_the_gyroscope_through_a_turn_of_the_field():
    errors = []
    for name in ("walk-texting", "walk-hand"):
        run, field = walk(name, seconds=45.0)
        field = turned_field(run, field, 1500, 1750, 30.0)
        truth = field_runs.magnetic_truth(run)
        scored = np.zeros(len(field), bool)
        scored[1500:2200] = True
        ours = fusion.fuse_causal(run.gyr_rads, run.acc_ms2, field, PERIOD_S, watch=True)
        assert ours.mag_disturbed[1550:1700].any()
        gyr, acc, mag = (fusion.to_vqf_frame(x) for x in (run.gyr_rads, run.acc_ms2, field))
        alone = frames.ned_enu_attitude(np.asarray(vqf.VQF(PERIOD_S).updateBatch(gyr, acc, mag)["quat9D"]))
        errors.append(
            [
                field_runs.rms_deg(field_runs.heading_error_deg(q, truth), scored, offset_removed=False)
                for q in (ours.quat_wxyz, alone)
            ]
        )
    ours_deg, alone_deg = np.mean(errors, axis=0)
    assert ours_deg < 0.9 * alone_deg  # measured 3.9 vs 4.8 deg (60-s walks, seeds 1-3: texting 2.3 vs 3.5, hand
    # 4.2 vs 6.7)
