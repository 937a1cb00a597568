"""Heading in motion end to end through the services (docs/design.md, "Heading in motion"): recordings replayed by
``magnet edge --replay`` through a calibrator and a compass, each in its own process on loopback, and the compass's
published headings compared with what nobody in the pipeline made.

- A BROAD trial (real IMU): the published headings agree with what ``magnet heading`` gives on the same file, with
  the record ``magnet fit`` gives it applied when accepted and none when refused (as the compass does): the live
  filter sees the same samples at the same times as the offline one.
- The moving simulator, every trajectory: a device is first tumbled (the calibrator fits and publishes its
  calibration), then it moves with its GNSS-like velocity on the wire (velocity aiding); the fused heading is scored
  against the simulator's truth.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from helpers import run_magnet
from motion_pipeline import Pipeline, joined, received

from magnet.attitude.heading import angle_difference_deg
from magnet.simulator import VEHICLE_TRAJECTORIES, SimulatedRun
from services.bench import motion

pytestmark = pytest.mark.integration

#: how the BROAD trials are replayed: samples per message, times faster than recorded
BROAD_BATCH, BROAD_SPEED = 50, 40.0
#: issue 8: published headings within this RMS (deg) of ``magnet heading`` on the same file
REPLAY_AGREEMENT_DEG = 0.3


def offline_headings(csv: Path, first_row: int, options: list[str]) -> np.ndarray:
    """``magnet heading`` (causal) on the CSV's rows from ``first_row`` on: heading_deg (N,)."""
    lines = csv.read_text().splitlines()
    part = csv.with_name(f"{csv.stem}-from-{first_row}.csv")
    part.write_text("\n".join([lines[0], *lines[1 + first_row :]]) + "\n")
    result = run_magnet("heading", str(part), *options)
    assert result.returncode == 0, result.stderr
    rows = result.stdout.splitlines()
    column = rows[0].split(",").index("heading_deg")
    return np.array([float(row.split(",")[column]) for row in rows[1:]])


@pytest.mark.parametrize("trial", motion.BROAD_TRIALS)
def test_broad_trial_replayed_through_the_services_gives_the_offline_headings(procs, tmp_path, datasets_dir, trial):
    log = motion.load_broad(datasets_dir / trial)
    csv = motion.write_csv(log, tmp_path / "broad.csv")
    fitted = run_magnet("fit", str(csv), "--method", "ellipsoid", "--out", str(tmp_path / "cal.json"))
    assert fitted.returncode in (0, 1), fitted.stderr
    # the same method on both sides: this test is about the services reproducing `magnet heading` with the same
    # record in force. The calibrator's default, auto, fits part of a trial as it arrives (trial 01: a gyro-ellipsoid
    # at 76 % coverage, residual 1.03 uT, held-out consistency 1.40 deg against 1.74 raw) and the compass applies it
    # from then on, mid-replay, which no single `magnet heading` run reproduces
    pipeline = Pipeline(procs, tmp_path, ["--method", "ellipsoid"], [])
    with pipeline.calibrations() as records, pipeline.headings() as headings:
        summary = pipeline.replay(csv, "broad-1", BROAD_SPEED, BROAD_BATCH)
        assert summary["published_samples"] == len(log.t_s)
        rows = received(headings, "broad-1", len(log.t_s), BROAD_BATCH, timeout_s=120)
    published = records.published("broad-1")
    # the calibrator judges the same data as `magnet fit`: what one refuses, the other does not put in force
    assert [r["accepted"] for r in published if r.get("accepted")] == ([True] if fitted.returncode == 0 else [])
    options = ["--calibration", str(tmp_path / "cal.json")] if fitted.returncode == 0 else []
    expected = offline_headings(csv, int(rows[0]), options)[rows - rows[0]]
    live = joined(headings, "broad-1", "heading_deg")
    difference = angle_difference_deg(live, expected)
    rms = float(np.sqrt(np.mean(difference**2)))
    print(
        f"{log.name} through edge -> calibrator -> compass: {len(live)} of {len(log.t_s)} headings received (from row "
        f"{rows[0]}), RMS {rms:.4f} deg (max {np.abs(difference).max():.4f}) from magnet heading"
    )
    assert rms <= REPLAY_AGREEMENT_DEG


#: the moving simulator through the services: samples per message, times faster than simulated. The velocity-aided
#: filter costs about 100 us a sample (the plain one 6), so four devices at 50x (20,000 samples/s) needed two seconds
#: of the compass's time a second: on a loaded CI machine Zenoh dropped two thirds of one device's messages. At 20x
#: the four need about 0.8 s a second
SIM_BATCH, SIM_SPEED = 25, 20.0
LOCATION, DATE = "50.45,30.52", "2026-01-01"  # the simulator's place and date
#: trajectory -> largest fused true-heading RMS (deg) against the truth, after the settling time, |pitch| < 60 deg.
#: fast-tumble meets issue 8's 0.3 deg; car and multirotor issue 20's 1.0 deg with the GNSS-like velocity the runs
#: carry (velocity aiding, docs/design.md "Heading in motion"); figure8 no worse than without it
SIM_REQUIRED_DEG = {"fast-tumble": 0.3, "figure8": 1.3, "car": 1.0, "multirotor": 1.0}


def simulator_csvs(tmp_path: Path) -> tuple[Path, dict[str, tuple[Path, SimulatedRun]]]:
    """The bench's sensor (``magnet bench motion``): a still tumble to calibrate it (CSV without gyroscope), and each
    moving trajectory (CSV with gyroscope) with its run (the truth)."""
    settings = motion.SimulatorSettings()
    errors = motion.simulated_sensor(settings)
    tumble = motion.tumble_run(errors, settings)
    tumble_csv = write_sim_csv(tumble, tmp_path / "tumble.csv", gyro=False)
    moving = {}
    for trajectory in VEHICLE_TRAJECTORIES:
        run = motion.moving_run(trajectory, errors, settings)
        moving[trajectory.value] = (write_sim_csv(run, tmp_path / f"{trajectory.value}.csv", gyro=True), run)
    return tumble_csv, moving


def write_sim_csv(run: SimulatedRun, path: Path, gyro: bool) -> Path:
    """The run as a CSV; with ``gyro`` the gyroscope and the GNSS-like velocity (vn,ve,vd; nan before the first fix)."""
    columns = [run.t_s[:, None], run.mag_ut, run.acc_ms2] + ([run.gyr_rads, run.vel_ned_ms] if gyro else [])
    header = "t_s,mx,my,mz,ax,ay,az" + (",gx,gy,gz,vn,ve,vd" if gyro else "")
    np.savetxt(path, np.hstack(columns), delimiter=",", header=header, comments="", fmt="%.9g")
    return path


def score(headings, device: str, run: SimulatedRun, settle_s: float) -> tuple[float, int]:
    """(RMS of the published true heading against the truth, samples scored): calibrated samples after the settling
    time with |pitch| < 60 deg."""
    rows = received(headings, device, len(run.t_s), SIM_BATCH, timeout_s=120)
    calibrated = joined(headings, device, "calibration_id") != ""
    scored = calibrated & (run.t_s[rows] >= settle_s) & (np.abs(run.pitch_deg[rows]) < motion.MAX_PITCH_DEG)
    error = angle_difference_deg(joined(headings, device, "true_heading_deg"), run.heading_deg[rows])
    return float(np.sqrt(np.mean(error[scored] ** 2))), int(scored.sum())


def test_moving_simulator_through_the_services_after_calibration(procs, tmp_path):
    tumble_csv, moving = simulator_csvs(tmp_path)
    pipeline = Pipeline(procs, tmp_path, ["--location", LOCATION], ["--location", LOCATION, "--date", DATE])
    settle_s = motion.SimulatorSettings().settle_s
    figures = {}
    with pipeline.calibrations() as records:
        for name in moving:
            pipeline.calibrate(records, tumble_csv, f"sim-{name}", SIM_SPEED, SIM_BATCH)
        with pipeline.headings() as headings:  # from here on: the moving runs only
            replays = [
                pipeline.start_replay(csv, f"sim-{name}", SIM_SPEED, SIM_BATCH) for name, (csv, _) in moving.items()
            ]
            for replay in replays:
                assert replay.wait(timeout=120) == 0
            for name, (_, run) in moving.items():
                figures[name] = score(headings, f"sim-{name}", run, settle_s)
    for name, (rms, count) in figures.items():
        print(f"{name}: fused true heading RMS {rms:.3f} deg over {count} samples through the services")
    for name, (rms, count) in figures.items():
        assert count > 0.5 * len(moving[name][1].t_s), name
        assert rms <= SIM_REQUIRED_DEG[name], name
