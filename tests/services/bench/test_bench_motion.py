"""`magnet bench motion`: the BROAD scoring is right (frames, mask, offset) and sees what fusion does."""

from __future__ import annotations

import numpy as np

from magnet import frames
from services.bench import motion


def test_reference_scores_zero_and_a_turned_reference_too(datasets_dir):
    log = motion.load_broad(datasets_dir / motion.BROAD_TRIALS[0])
    reference = log.reference_heading_deg()
    assert log.score(reference) < 1e-9
    assert log.score(reference + 123.0) < 1e-9  # the optical frame's north is arbitrary: one offset removed
    assert 0.4 < log.scored.mean() < 0.8  # movement phase only, reference present, |pitch| < 60 deg


def test_project_frame_gravity_points_down_and_matches_the_reference(datasets_dir):
    log = motion.load_broad(datasets_dir / motion.BROAD_TRIALS[0])
    still = ~log.scored & np.all(np.isfinite(log.ref_quat_wxyz), axis=1)
    down = frames.down_in_body(log.ref_quat_wxyz[still])
    measured = -log.acc_ms2[still] / np.linalg.norm(log.acc_ms2[still], axis=1, keepdims=True)
    assert np.median(np.einsum("ij,ij->i", down, measured)) > np.cos(np.radians(3.0))


def test_fusion_beats_accelerometer_tilt_on_every_trial(datasets_dir):
    rows = {(trial, estimator): rms for trial, estimator, rms in motion.broad_rows(datasets_dir)}
    for trial in {trial for trial, _ in rows}:
        assert rows[(trial, "accelerometer tilt")] > 5.0
        assert rows[(trial, "fused causal")] < 1.2
        assert rows[(trial, "fused offline")] < rows[(trial, "fused causal")]


def test_simulator_rows_score_against_the_truth():
    settings = motion.SimulatorSettings(seconds=30.0)  # 30 s: tilt 44, causal 0.37, offline 0.07 (40 s: 43, 0.31, 0.08)
    rows = {
        estimator: (trial, rms)
        for trial, estimator, rms in motion.simulator_rows(settings, [motion.Trajectory.FAST_TUMBLE])
    }
    assert rows["fused causal"][0] == "fast-tumble (cal: own data)"  # a tumble covers the sphere: own data accepted
    assert rows["accelerometer tilt"][1] > 10.0
    assert rows["fused offline"][1] < rows["fused causal"][1] < 0.5


def test_linear_acceleration_is_what_the_car_loses():
    """Fed the accelerometer without the run's linear acceleration (what velocity aiding could give at best), the
    causal filter's car heading is several times better: the acceleration, not the filter's set-up, is the limit."""
    rows = {
        estimator: rms
        for _, estimator, rms in motion.simulator_rows(
            motion.SimulatorSettings(seconds=20.0), [motion.Trajectory.CAR]
        )  # 20 s: bound 1.2, causal 18.3, aided 0.45 (30 s: 1.3, 15.1, 0.32)
    }
    assert rows[motion.BOUND_ESTIMATOR] < 2.0 < 3 * rows[motion.BOUND_ESTIMATOR] < rows["fused causal"]
    assert rows["fused causal, velocity aided"] < rows["fused causal"] / 3  # the GNSS-like velocity gives it back


def test_without_linear_acceleration_leaves_gravity_and_noise():
    settings = motion.SimulatorSettings(seconds=20.0)
    run = motion.moving_run(motion.Trajectory.CAR, motion.simulated_sensor(settings), settings)
    gravity = np.linalg.norm(motion.without_linear_acceleration(run), axis=1)
    assert np.abs(gravity - 9.80665).max() < 0.15  # the accelerometer's noise (0.02 m/s^2 per axis) only
    assert np.abs(np.linalg.norm(run.acc_ms2, axis=1) - 9.80665).max() > 0.3  # the car does accelerate
