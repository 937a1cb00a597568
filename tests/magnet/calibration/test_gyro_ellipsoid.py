"""Calibration from the gyroscope (``gyro-ellipsoid``, magnet.calibration.gyro_ellipsoid) against simulator truth,
chosen by name in ``fit`` and ``magnet fit``, refused clearly without a gyroscope."""

from __future__ import annotations

import dataclasses
import json
import time
from pathlib import Path

import numpy as np
import pytest

from magnet.calibration import FitError, FitInput, Method, fit, fit_shape
from magnet.model import KNOWN_METHODS, Calibration
from magnet.simulator import SensorErrors, SimulatorConfig, Trajectory, simulate
from services.cli import main

PERIOD_S = 0.01


@pytest.fixture(scope="module")
def tumbled():
    """5 minutes at 100 Hz of a fast tumble: hard iron up to the field, 10 % soft iron, 2-4 deg misalignment."""
    rng = np.random.default_rng(4)
    errors = SensorErrors.random(
        rng, 50.0, hard_iron_max_ratio=1.0, soft_iron_max=0.1, noise_ut=0.3, gyro_noise_rads=0.002
    )
    errors = dataclasses.replace(errors, misalignment_deg=(2.0, -3.0, 4.0))
    run = simulate(SimulatorConfig(trajectory=Trajectory.FAST_TUMBLE, rate_hz=100.0, count=30_000, errors=errors))
    return run, errors.true_calibration(run.earth.total_ut)


def test_chosen_by_name_it_recovers_offset_soft_iron_and_the_rotation_into_the_imu_frame(tumbled):
    run, truth = tumbled
    started = time.process_time()  # CPU time: a loaded machine (load 13 on 2 cores) stretches the wall clock 5x
    cal, _ = fit_shape(
        FitInput(run.mag_ut, gyr_rads=run.gyr_rads, period_s=PERIOD_S, field_ut=run.earth.total_ut), "gyro-ellipsoid"
    )
    assert time.process_time() - started < 1.0  # 5 minutes at 100 Hz
    assert cal.method == Method.GYRO_ELLIPSOID.value == "gyro-ellipsoid"
    np.testing.assert_allclose(cal.offset, truth.offset, atol=0.02)  # uT, hard iron up to the field itself
    # the matrix holds the 2-4 deg misalignment (an ellipsoid fit cannot see it): recovered to 0.1 %
    assert np.abs(cal.matrix - truth.matrix).max() < 0.001 * np.abs(truth.matrix).max()


def test_with_its_gate_it_is_accepted_and_beats_the_plain_ellipsoid_on_held_out_data(tumbled):
    run, _ = tumbled
    part = slice(0, 10_000)  # 100 s (the 5 minutes with the gate: ``magnet bench fit``)
    data = FitInput(
        run.mag_ut[part],
        acc=run.acc_ms2[part],
        gyr_rads=run.gyr_rads[part],
        period_s=PERIOD_S,
        field_ut=run.earth.total_ut,
    )
    gyro = fit(data, "gyro-ellipsoid")
    plain = fit(data, "ellipsoid")
    assert gyro.accepted, gyro.reason
    held_gyro, held_plain = gyro.quality["holdout_consistency_deg"], plain.quality["holdout_consistency_deg"]
    # the ellipsoid leaves the 2-4 deg misalignment in; the gyroscope fit takes it out
    assert held_gyro < held_plain - 1.0
    # and the record is one every reader accepts (store, wire, export check the method against KNOWN_METHODS)
    assert "gyro-ellipsoid" in KNOWN_METHODS
    again = Calibration.from_dict(gyro.to_dict())
    assert again.method == "gyro-ellipsoid"
    np.testing.assert_allclose(again.matrix, gyro.matrix)


def test_without_a_gyroscope_it_is_refused_with_what_to_do(tumbled):
    run, _ = tumbled
    with pytest.raises(FitError, match=r"gyroscope samples \(gx, gy, gz"):
        fit(FitInput(run.mag_ut[:3000], acc=run.acc_ms2[:3000]), "gyro-ellipsoid")
    with pytest.raises(FitError, match="sample period"):
        fit(FitInput(run.mag_ut[:3000], gyr_rads=run.gyr_rads[:3000]), "gyro-ellipsoid")
    with pytest.raises(FitError, match="shape of the magnetometer samples"):
        fit(FitInput(run.mag_ut[:3000], gyr_rads=run.gyr_rads[:10], period_s=PERIOD_S), "gyro-ellipsoid")


def test_rotation_about_one_axis_is_refused_with_what_to_do():
    t = np.arange(3000) * PERIOD_S
    angle = 0.5 * t
    earth = np.array([20.0, 0.0, 45.0])
    mag = np.stack([np.cos(angle) * earth[0], -np.sin(angle) * earth[0], np.full_like(t, earth[2])], axis=-1)
    gyr = np.tile([0.0, 0.0, 0.5], (len(t), 1))
    with pytest.raises(FitError, match="every axis"):
        fit_shape(FitInput(mag + 10.0, gyr_rads=gyr, period_s=PERIOD_S), "gyro-ellipsoid")
    still = np.zeros_like(gyr)
    with pytest.raises(FitError, match="turn the device about every axis"):
        fit_shape(FitInput(mag + 10.0, gyr_rads=still, period_s=PERIOD_S), "gyro-ellipsoid")


def _csv(path: Path, run, columns: str) -> Path:
    parts = {"t_s": run.t_s[:, None], "m": run.mag_ut, "a": run.acc_ms2, "g": run.gyr_rads}
    names = {"t_s": "t_s", "m": "mx,my,mz", "a": "ax,ay,az", "g": "gx,gy,gz"}
    keys = columns.split()
    table = np.hstack([parts[k][:6000] for k in keys])
    np.savetxt(path, table, delimiter=",", header=",".join(names[k] for k in keys), comments="", fmt="%.9g")
    return path


def test_magnet_fit_takes_it_by_name_and_refuses_a_file_without_gyroscope_columns(tumbled, tmp_path, capsys):
    run, truth = tumbled
    good = _csv(tmp_path / "gyro.csv", run, "t_s m a g")
    out = tmp_path / "cal.json"
    assert main(["fit", str(good), "--method", "gyro-ellipsoid", "--field-ut", "50", "--out", str(out)]) == 0
    record = Calibration.from_dict(json.loads(out.read_text()))
    assert record.method == "gyro-ellipsoid" and record.accepted
    np.testing.assert_allclose(record.offset, truth.offset, atol=0.1)
    capsys.readouterr()
    bare = _csv(tmp_path / "bare.csv", run, "t_s m a")
    assert main(["fit", str(bare), "--method", "gyro-ellipsoid"]) == 2
    err = capsys.readouterr().err
    assert "gx,gy,gz" in err and "Traceback" not in err and len(err.strip().splitlines()) == 1


def test_in_a_figure8_it_is_accepted_without_full_coverage_and_nearer_the_truth_than_the_ellipsoid():
    """A hand-held figure-8 covers under half the sphere: the ellipsoid is refused for coverage (and its offset is
    off by most of a uT); the gyroscope's turns determine gyro-ellipsoid, so coverage is not asked of it."""
    rng = np.random.default_rng(7)
    errors = SensorErrors.random(
        rng,
        50.0,
        hard_iron_max_ratio=1.0,
        soft_iron_max=0.1,
        noise_ut=0.3,
        gyro_bias_rads=rng.uniform(-0.005, 0.005, 3),
        gyro_noise_rads=0.002,
    )
    run = simulate(SimulatorConfig(trajectory=Trajectory.FIGURE8, rate_hz=100.0, count=6000, errors=errors, seed=7))
    truth = errors.true_calibration(run.earth.total_ut)
    data = FitInput(run.mag_ut, acc=run.acc_ms2, gyr_rads=run.gyr_rads, period_s=PERIOD_S, field_ut=run.earth.total_ut)
    gyro, plain = fit(data, "gyro-ellipsoid"), fit(data, "ellipsoid")
    assert gyro.accepted, gyro.reason
    assert gyro.quality.coverage < 0.6 and not plain.accepted and "coverage" in plain.reason
    gyro_error, plain_error = (np.abs(c.offset - truth.offset).max() for c in (gyro, plain))
    assert gyro_error < 0.2 and gyro_error < plain_error / 2


def test_a_magnetometer_that_lags_the_gyroscope_is_found_out_and_calibrated_all_the_same(tumbled):
    run, truth = tumbled
    late = np.vstack([np.repeat(run.mag_ut[:1], 2, axis=0), run.mag_ut[:-2]])  # each reading 2 samples (20 ms) late
    cal, shape = fit_shape(
        FitInput(late, gyr_rads=run.gyr_rads, period_s=PERIOD_S, field_ut=run.earth.total_ut), "gyro-ellipsoid"
    )
    assert shape.note == "magnetometer +20 ms behind the gyroscope"
    np.testing.assert_allclose(cal.offset, truth.offset, atol=0.05)
    assert np.abs(cal.matrix - truth.matrix).max() < 0.002 * np.abs(truth.matrix).max()
