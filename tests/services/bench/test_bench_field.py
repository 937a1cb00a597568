"""``magnet bench field``: its heading error, its baselines and one short run through the services' cores."""

import argparse

import numpy as np
import pytest

from magnet import frames
from magnet import simulator as sim
from services.bench import field, field_runs, parse_seeds


def test_heading_error_is_the_turn_about_the_vertical_at_any_attitude():
    yaw = np.array([10.0, 200.0, 350.0, 45.0])
    pitch = np.array([0.0, 30.0, 85.0, -89.0])  # up to a phone standing upright
    roll = np.array([0.0, -40.0, 120.0, 10.0])
    truth = frames.euler_to_quaternion(yaw, pitch, roll)
    estimate = frames.rotate_heading(truth, 7.0)  # the same attitude turned 7 deg about the vertical
    np.testing.assert_allclose(field_runs.heading_error_deg(estimate, truth), 7.0, atol=1e-9)
    errors = np.array([7.0, 9.0, 5.0, np.nan])
    assert field_runs.rms_deg(errors, np.ones(4, bool)) == pytest.approx(np.sqrt(8.0 / 3.0))
    assert field_runs.rms_deg(errors, np.ones(4, bool), offset_removed=False) == pytest.approx(np.sqrt(155.0 / 3.0))
    assert np.isnan(field_runs.rms_deg(errors, np.zeros(4, bool)))


def test_the_plain_sphere_fit_finds_a_phones_hard_iron():
    errors = sim.SensorErrors.phone(np.random.default_rng(3), 50.0, noise_ut=0.0, soft_iron=np.eye(3))
    errors = sim.SensorErrors(hard_iron_ut=errors.hard_iron_ut)
    run = sim.simulate(sim.SimulatorConfig(count=2000, errors=errors))
    np.testing.assert_allclose(run.mag_ut - field_runs.sphere_fit_field(run.mag_ut), run.mag_ut - run.true_field_ut)


def test_a_short_run_through_the_cores_and_the_commands():
    settings = field_runs.FieldSettings(seconds=30.0)
    figures = field.score_run("robot", 5, settings)
    assert figures["motion"] == "robot" and figures["group"] == "planar"
    # a phone's hard iron (6-15 times the field) makes the raw field useless, a sphere fit mends it
    assert figures["vqf_raw"] > 10.0 > 3.0 > figures["sphere_vqf"]
    for key in ("fit_causal", "fit_offline", "vqf_6d", "vqf_6d_offline", "sphere_vqf_offline"):
        assert np.isfinite(figures[key])
    assert figures["first_record_s"] is None or 0.0 < figures["first_record_s"] <= 30.0
    line = field.motion_line("robot", [figures])
    assert line.startswith("robot") and len(line.split()) == 2 + len(field.COLUMNS)


def test_verdicts_count_records_and_compare_disturbed_walks_with_the_gyroscope():
    rows = [
        {"motion": "a", "group": "walk", "seed": 1, "first_record_s": 30.0, "live_abs": 2.0, "live": 1.0},
        {"motion": "a", "group": "walk", "seed": 2, "first_record_s": None, "live_abs": np.nan, "live": np.nan},
        {"motion": "b", "group": "disturbed", "seed": 1, "live": 9.0, "vqf_6d": 8.0},
    ]
    walk, planar, disturbed = field.verdict_lines(rows)
    assert "1/2 runs with a record within 60 s, 1/2 with live heading within 3 deg" in walk
    assert planar.startswith("planar: 0/0")
    assert "worse than 6D: b seed 1" in disturbed


def test_seeds_option():
    assert parse_seeds("1,2, 3") == (1, 2, 3)
    for bad in ("", "a", "-1"):
        with pytest.raises(argparse.ArgumentTypeError):
            parse_seeds(bad)


def test_vehicles_with_gnss_send_their_velocity(tmp_path):
    # a car's and a boat's navigation gives the compass its velocity (the filter's tilt then ignores the vehicle's own
    # accelerations); the walks and the indoor robot send none
    assert {name for name, motion in field_runs.MOTIONS.items() if motion.gnss} == {"car", "boat"}
    run = field_runs.field_run(field_runs.MOTIONS["car"], 5, field_runs.FieldSettings(seconds=4.0))
    with_velocity = field.write_run_csv(run, tmp_path / "car.csv", velocity=True).read_text().splitlines()
    assert with_velocity[0].endswith(",vn,ve,vd") and len(with_velocity) == len(run.t_s) + 1
    last = np.array(with_velocity[-1].split(","), dtype=float)
    np.testing.assert_allclose(last[-3:], run.vel_ned_ms[-1], rtol=1e-6)
    without = field.write_run_csv(run, tmp_path / "plain.csv").read_text().splitlines()
    assert without[0] == "t_s,mx,my,mz,ax,ay,az,gx,gy,gz"


def test_the_wand_line_counts_runs_worse_than_vqf_with_the_same_filter():
    def row(seed, fit_c, fit_o, vqf_c, vqf_o):
        return {"motion": "wand, calibrated", "group": "wand", "seed": seed, "fit_causal": fit_c,
                "fit_offline": fit_o, "vqf_raw": vqf_c, "vqf_raw_offline": vqf_o}  # fmt: skip

    rows = [
        row(1, 1.04, 0.50, 1.0, 0.5),  # within 5 %
        row(2, 1.06, 0.40, 1.0, 0.5),  # causal worse
        row(3, 0.90, 0.60, 1.0, 0.5),  # offline worse (against vqf's offline, not its causal)
        {"motion": "car", "group": "planar", "seed": 1, "fit_causal": 9.0, "vqf_raw": 1.0},
    ]
    assert field.worse_than_vqf(rows[0]) == [] and field.worse_than_vqf(rows[1]) == ["c"]
    assert field.worse_than_vqf(rows[2]) == ["o"]
    (line,) = field.wand_lines(rows)
    assert line.startswith("wand: 2/3 runs with fit c or fit o more than 5 % worse than vqf raw")
    assert "seed 2 c 1.060 vs 1.000" in line and "seed 3 o 0.600 vs 0.500" in line and "seed 1 " not in line
    assert field.wand_lines(rows[3:]) == []
    assert field.verdict_lines(rows[:3])[-1] == line  # the bench prints it after the other checks


def test_the_wand_is_a_maker_calibrated_sensor_in_the_bench():
    motion = field_runs.MOTIONS["wand, calibrated"]
    assert motion.trajectory is sim.Trajectory.WAND and motion.sensor == "calibrated" and motion.group == "wand"
    run = field_runs.field_run(motion, 1, field_runs.FieldSettings(seconds=4.0))
    assert np.linalg.norm(run.errors.hard_iron_ut) < 1.0
    assert all(m.sensor == "phone" for name, m in field_runs.MOTIONS.items() if name != "wand, calibrated")
