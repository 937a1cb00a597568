"""Motor interference: the model on the record, its fit from a log (within 5 % per axis), and the compass taking it
out (heading error at full throttle under 1 deg, against the uncompensated figure)."""

from __future__ import annotations

import functools
import json
from pathlib import Path

import numpy as np
import pytest
from compass_steps import compass_core, heading_batches

from magnet import wire
from magnet.attitude.heading import angle_difference_deg
from magnet.calibration import FitError, FitInput, fit
from magnet.calibration.motor_fit import fit_motor, fit_with_motor
from magnet.earth.expected import Earth
from magnet.frames import ned_to_body_euler
from magnet.model import Calibration
from magnet.motor import MotorModel, interference_pct
from magnet.simulator import Motors, SensorErrors, SimulatorConfig, simulate
from magnet.simulator.motion import G_NED
from services.cli import main

ERRORS = SensorErrors(
    hard_iron_ut=(20.0, -15.0, 8.0),
    soft_iron=((1.05, 0.02, 0.0), (0.02, 0.97, 0.01), (0.0, 0.01, 1.02)),
    noise_ut=0.3,
)
#: 10 uT at full current (40 A), on all three axes
MOTORS = Motors.with_full_field(10.0, (0.6, -0.5, 0.62))


@functools.cache
def ground_calibration() -> Calibration:
    """The sensor calibrated on the ground, motors off (a tumble)."""
    tumble = simulate(SimulatorConfig(trajectory="tumble", count=3000, errors=ERRORS, seed=1))
    return fit(FitInput(tumble.mag_ut, field_ut=tumble.earth.total_ut), "ellipsoid")


@functools.cache
def flight():  # type: ignore[no-untyped-def]
    """A multirotor flight (2 min at 50 Hz) from hover to full throttle and back, again and again."""
    return simulate(SimulatorConfig(trajectory="multirotor", count=6000, errors=ERRORS, seed=3, motors=MOTORS))


def test_the_simulated_motors_add_their_field_at_full_current() -> None:
    run = flight()
    assert run.throttle is not None and run.current_a is not None
    # the profile from hover to full, times the thrust the flight needs (about 1 g, more in banks, less in descents)
    assert 0.8 * MOTORS.hover_throttle < run.throttle.min() < MOTORS.hover_throttle and run.throttle.max() == 1.0
    np.testing.assert_allclose(np.linalg.norm(np.asarray(MOTORS.ut_per_a)) * 40.0, 10.0)
    clean = simulate(SimulatorConfig(trajectory="multirotor", count=6000, errors=ERRORS, seed=3))
    added = np.linalg.solve(np.asarray(ERRORS.soft_iron), (run.mag_ut - clean.mag_ut).T).T
    top = run.throttle > 0.999
    np.testing.assert_allclose(np.linalg.norm(added[top], axis=1), 10.0, atol=0.05)


def test_fit_from_a_flight_log_recovers_each_axis_within_5_percent() -> None:
    run, calibration = flight(), ground_calibration()
    result = fit_motor(calibration.apply(run.mag_ut), run.current_a, "current", run.earth.total_ut)
    error = np.abs(result.model.coefficients / np.asarray(MOTORS.ut_per_a) - 1.0)
    print(f"per-axis error of the fitted motor field: {np.round(100 * error, 2)} %")
    assert result.way == "moving" and error.max() < 0.05
    # compassmot's figure: |m| * largest current / largest throttle / |B| = 10 uT / |B|
    assert result.interference_pct == pytest.approx(1000.0 / run.earth.total_ut, rel=0.05)


def test_joint_fit_of_calibration_and_motors_from_a_tumble_with_motors_running() -> None:
    run = simulate(SimulatorConfig(trajectory="tumble", count=6000, errors=ERRORS, seed=2, motors=MOTORS))
    strength = run.earth.total_ut
    calibration, result = fit_with_motor(
        run.mag_ut, run.current_a, "current", lambda mag: fit(FitInput(mag, field_ut=strength), "ellipsoid"), strength
    )
    assert np.abs(result.model.coefficients / np.asarray(MOTORS.ut_per_a) - 1.0).max() < 0.05
    np.testing.assert_allclose(calibration.offset, ERRORS.hard_iron_ut, atol=0.3)
    assert calibration.motor is result.model


def test_still_compassmot_run_is_fitted_per_axis() -> None:
    rng = np.random.default_rng(0)
    current = np.linspace(0.0, 30.0, 300)
    field = np.array([18.0, 1.0, 47.0]) + current[:, None] * np.array([0.1, -0.2, 0.05])
    result = fit_motor(field + 0.2 * rng.standard_normal(field.shape), current, "current", 50.0)
    assert result.way == "still"
    np.testing.assert_allclose(result.model.coefficients, [0.1, -0.2, 0.05], atol=0.005)
    with pytest.raises(FitError, match="changed by only"):
        fit_motor(field[:100], np.full(100, 10.0), "current")


def _full_throttle_heading_error(calibration: Calibration) -> float:
    """RMS heading error (deg) of the compass at full throttle (> 95 %), the attitude's tilt given exactly (the
    accelerometer of a vehicle at rest in that attitude), so the error is the magnetometer's."""
    run = flight()
    acc = ned_to_body_euler(-G_NED, run.heading_deg, run.pitch_deg, run.roll_deg)
    compass = compass_core(Earth(), window=1)
    assert compass.accept_calibration(wire.encode_calibration("q", calibration, 1), "magnet/q/calibration", "magnet")
    batch = wire.RawBatch("q", 0, "mav", np.arange(len(run.t_s)), run.mag_ut, acc, current_a=run.current_a)
    [out] = heading_batches(compass, [batch])
    top = (run.throttle > 0.95) & (np.abs(run.pitch_deg) < 60)
    error = angle_difference_deg(out.heading_deg[top], run.magnetic_heading_deg[top])
    return float(np.sqrt(np.mean(error**2)))


def test_compass_takes_the_motors_field_out_at_full_throttle() -> None:
    run, calibration = flight(), ground_calibration()
    result = fit_motor(calibration.apply(run.mag_ut), run.current_a, "current", run.earth.total_ut)
    compensated = _full_throttle_heading_error(calibration.replace(motor=result.model))
    uncompensated = _full_throttle_heading_error(calibration)
    # the floor: the exact motor model; 0.3 uT of noise on a 19 uT horizontal field, sample by sample, unsmoothed
    floor = _full_throttle_heading_error(calibration.replace(motor=MotorModel("current", np.array(MOTORS.ut_per_a))))
    print(
        f"heading RMS at full throttle: {compensated:.3f} deg compensated (exact model {floor:.3f}), "
        f"{uncompensated:.2f} deg without"
    )
    assert compensated < 1.0 and compensated < floor + 0.05
    assert uncompensated > 10.0


def test_motor_model_on_the_record_round_trips_and_is_checked() -> None:
    calibration = ground_calibration().replace(motor=MotorModel("current", np.array([0.1, -0.2, 0.3])))
    record = wire.calibration_record("d", calibration, 5)
    assert record["motor_ut_per_a"] == [0.1, -0.2, 0.3] and "motor_ut_per_throttle" not in record
    back = wire.calibration_from_record(record).calibration
    assert back.motor is not None and back.motor.kind == "current"
    assert back.content_id == calibration.content_id != ground_calibration().content_id
    assert "motor_ut_per_a" not in ground_calibration().to_dict()
    for bad, text in (
        ({"motor_ut_per_a": [0.1, 0.2]}, "3 finite numbers"),
        ({"motor_ut_per_a": [True, 0.0, 0.0]}, "list of 3 numbers"),
        ({"motor_ut_per_a": [0.1, "x", 0.0]}, "3 numbers"),
        ({"motor_ut_per_a": [500.0, 0.0, 0.0]}, "exceeds 100"),
        ({"motor_ut_per_a": [0.1, 0, 0], "motor_ut_per_throttle": [1.0, 0, 0]}, "not both"),
    ):
        with pytest.raises(wire.WireError, match=text):
            wire.calibration_from_record({**record, **bad})
    throttle = MotorModel("throttle", np.array([3.0, 4.0, 0.0]))
    assert interference_pct(throttle, 50.0) == pytest.approx(10.0)


def test_magnet_fit_motor_writes_the_motor_model_and_refuses_a_log_without_current(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    run = simulate(SimulatorConfig(trajectory="tumble", count=4000, errors=ERRORS, seed=2, motors=MOTORS))
    table = np.column_stack([run.t_s, run.mag_ut, run.acc_ms2, run.current_a])
    path = tmp_path / "motors.csv"
    np.savetxt(path, table, delimiter=",", header="t_s,mx,my,mz,ax,ay,az,current_a", comments="", fmt="%.9g")
    strength = f"{run.earth.total_ut:.4f}"
    assert main(["fit", str(path), "--method", "ellipsoid", "--field-ut", strength, "--motor", "current"]) == 0
    record = json.loads(capsys.readouterr().out)
    fitted = np.asarray(record["motor_ut_per_a"])
    assert np.abs(fitted / np.asarray(MOTORS.ut_per_a) - 1.0).max() < 0.05
    assert record["quality"]["motor_interference_pct"] == pytest.approx(1000.0 / run.earth.total_ut, rel=0.05)
    bare = tmp_path / "bare.csv"
    np.savetxt(bare, table[:, :7], delimiter=",", header="t_s,mx,my,mz,ax,ay,az", comments="", fmt="%.9g")
    assert main(["fit", str(bare), "--method", "ellipsoid", "--motor", "throttle"]) == 2
    refused = capsys.readouterr()
    assert "needs a throttle column" in refused.err
    assert len(refused.err.strip().splitlines()) == 1 and not refused.out
