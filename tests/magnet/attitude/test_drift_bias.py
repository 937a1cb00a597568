"""The gyroscope's bias about the vertical from the field's heading drift (magnet.attitude.drift_bias)."""

from __future__ import annotations

import math

import numpy as np
import vqf

from magnet.attitude import drift_bias as vb
from magnet.attitude import fusion
from services.bench import field_runs as fr


def _drift_case(bias_dps: float, seed: int = 0) -> tuple[np.ndarray, np.ndarray, float]:
    """A walker-like up axis (mostly body z, swaying) over 90 s at 10 Hz, and the field's angle drifting by the
    bias about it, with 2 deg of tilt errors correlated over 2 s and an offset."""
    rng = np.random.default_rng(seed)
    period = 0.1
    t = np.arange(900) * period
    up = np.column_stack([0.2 * np.sin(2 * np.pi * t / 7.0), 0.1 * np.cos(2 * np.pi * t / 3.0), np.ones_like(t)])
    up /= np.linalg.norm(up, axis=1)[:, None]
    bias = np.array([0.1, -0.2, 1.0]) * math.radians(bias_dps)
    drift = np.cumsum(up @ bias) * period
    errors = np.convolve(rng.standard_normal(len(t)), np.ones(20) / math.sqrt(20), mode="same") * math.radians(2.0)
    return math.remainder(1.0, math.tau) + drift + errors, up, period


def test_fit_drift_finds_the_bias_about_the_up_axis() -> None:
    for bias_dps in (0.4, -0.25, 0.0):
        angle, up, period = _drift_case(bias_dps)
        found = vb.fit_drift(np.angle(np.exp(1j * angle)), up, period)  # wrapped, as atan2 gives it
        assert found is not None
        expected = math.radians(bias_dps) * float(found.up @ np.array([0.1, -0.2, 1.0]))
        assert abs(found.along_up_rads - expected) < math.radians(0.03)
        assert found.sigma_rads < math.radians(0.05)
        assert np.allclose(found.bias_rads, found.along_up_rads * found.up)


def test_fit_drift_resists_a_disturbed_stretch_and_needs_enough_samples() -> None:
    angle, up, period = _drift_case(0.3, seed=1)
    angle[300:330] += math.radians(40.0)  # a steel door passed: 3 s of the field turned
    found = vb.fit_drift(angle, up, period)
    assert found is not None
    assert abs(found.along_up_rads - math.radians(0.3) * float(found.up @ np.array([0.1, -0.2, 1.0]))) < math.radians(
        0.05
    )
    short = angle.copy()
    short[int(vb.MIN_SPAN_S / period) - 5 :] = np.nan
    assert vb.fit_drift(short, up, period) is None


def test_a_device_that_rested_keeps_vqfs_own_bias() -> None:
    period = 0.02
    count = 1500
    gyr = np.tile([0.0, 0.0, math.radians(0.3)], (count, 1))  # still, with a bias about the vertical
    acc = np.tile([0.0, 0.0, 9.81], (count, 1))
    field = np.tile([20.0, 0.0, -45.0], (count, 1))
    first = vqf.offlineVQF(gyr, acc, field, period)
    out_gyr, params, found = vb.offline_correction(gyr, field, period, {}, first)
    assert found == [] and params == {} and out_gyr is gyr


def test_offline_heading_of_a_walk_is_better_with_the_bias_found() -> None:
    """A simulated phone in a pocket (tuning seed 1, 60 s): the offline heading after the constant offset, with the
    simulator's true calibration, with and without the bias about the vertical found from the field."""
    settings = fr.FieldSettings(seconds=60.0)
    run = fr.field_run(fr.MOTIONS["walk-pocket"], 1, settings)
    field = run.errors.true_calibration(float(run.earth.total_ut)).apply(run.mag_ut)
    settled = run.t_s >= settings.settle_s
    truth = fr.magnetic_truth(run)
    figures = {}
    for on in (False, True):
        fused = fusion.fuse_offline(run.gyr_rads, run.acc_ms2, field, 1.0 / settings.rate_hz, vertical_bias=on)
        figures[on] = fr.rms_deg(fr.heading_error_deg(fused.quat_wxyz, truth), settled)
    assert figures[True] < 0.8 * figures[False], figures


def test_a_long_log_gets_a_bias_per_part() -> None:
    """A device turning about its vertical (level, 25 Hz, never still) for 700 s whose bias about the vertical steps
    from 0.3 to -0.2 deg/s half-way: three parts, each with its own bias, the first and last within 0.03 deg/s."""
    period = 0.04
    t = np.arange(int(700.0 / period)) * period
    rate = np.radians(15.0 + 5.0 * np.sin(2 * np.pi * t / 40.0))  # true turn rate about the vertical (vqf's z up)
    yaw = np.cumsum(rate) * period
    bias = np.where(t < 350.0, math.radians(0.3), math.radians(-0.2))
    gyr = np.column_stack([np.zeros_like(t), np.zeros_like(t), rate + bias])
    acc = np.tile([0.0, 0.0, 9.81], (len(t), 1))
    # the Earth's field (north 20, up -45 uT) in body axes of a level device turned by yaw about z (ENU, FLU)
    field = np.column_stack([20.0 * np.sin(yaw), 20.0 * np.cos(yaw), np.full_like(t, -45.0)])
    first = vqf.offlineVQF(gyr, acc, field, period)
    out_gyr, params, found = vb.offline_correction(gyr, field, period, {}, first, lengthen=False)
    assert params == {} and len(found) == 3
    assert abs(found[0].along_up_rads - math.radians(0.3)) < math.radians(0.03)
    assert abs(found[2].along_up_rads + math.radians(0.2)) < math.radians(0.03)
    assert np.allclose(out_gyr[-1], gyr[-1] - found[2].bias_rads)


def test_a_whole_turn_of_the_field_passing_an_object_leaves_no_step() -> None:
    """3 s in which a passing object turns the field's angle through a whole turn (as a 55 uT steel door does): the
    drift before and after it stays one line, and the bias is found as without the object."""
    angle, up, period = _drift_case(0.3, seed=2)
    clean = vb.fit_drift(angle, up, period)
    spun = angle.copy()
    spun[400:430] -= np.linspace(0.0, 2.0 * np.pi, 30)  # the angle turned once, back where it was after
    found = vb.fit_drift(np.angle(np.exp(1j * spun)), up, period)
    assert clean is not None and found is not None
    assert abs(found.along_up_rads - clean.along_up_rads) < math.radians(0.02)
    assert found.residual_rad < math.radians(5.0)
