"""`magnet heading` with a gyroscope: fused (causal / --offline), sample period from t_s or --rate, clear errors."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from fusion_helpers import RATE_HZ, rotating_device
from helpers import run_magnet as magnet

from magnet import frames
from magnet.attitude.heading import HeadingFlag, angle_difference_deg

pytestmark = pytest.mark.integration


def read_output(text: str) -> dict[str, np.ndarray]:
    lines = text.strip().splitlines()
    table = np.array([[float(v) for v in line.split(",")] for line in lines[1:]])
    return {name: table[:, i] for i, name in enumerate(lines[0].split(","))}


@pytest.fixture(scope="module")
def device():
    return rotating_device(seconds=40.0)


def write(path: Path, device, with_time: bool = True, with_gyro: bool = True) -> Path:
    gyr, acc, mag, _ = device
    columns, names = [mag, acc / 9.80665], ["mx,my,mz", "ax,ay,az"]  # acc in g: recognised and converted
    if with_gyro:
        columns.append(gyr)
        names.append("gx,gy,gz")
    if with_time:
        columns.insert(0, (np.arange(len(gyr)) / RATE_HZ)[:, None])
        names.insert(0, "t_s")
    np.savetxt(path, np.hstack(columns), delimiter=",", header=",".join(names), comments="", fmt="%.9g")
    return path


@pytest.mark.parametrize("offline", [False, True])
def test_fused_heading_and_quaternion_follow_the_truth(tmp_path: Path, device, offline: bool):
    csv = write(tmp_path / "moving.csv", device)
    result = magnet("heading", str(csv), "--declination", "4", *(["--offline"] if offline else []))
    assert result.returncode == 0, result.stderr
    out = read_output(result.stdout)
    heading, pitch, _ = frames.quaternion_to_euler(device[3])
    settled = (np.arange(len(heading)) >= 20 * RATE_HZ) & (np.abs(pitch) < 60)
    error = angle_difference_deg(out["heading_deg"], heading)[settled]
    assert np.sqrt(np.mean(error**2)) < 1.0
    assert np.all(out["flags"].astype(int) & HeadingFlag.FUSED)
    assert not np.any(out["flags"].astype(int) & HeadingFlag.CALIBRATED)
    quat = np.column_stack([out[k] for k in ("qw", "qx", "qy", "qz")])
    true_heading, _, _ = frames.quaternion_to_euler(quat)
    assert np.abs(angle_difference_deg(true_heading, out["true_heading_deg"])).max() < 1e-3
    assert np.abs(angle_difference_deg(out["true_heading_deg"], out["heading_deg"] + 4)).max() < 1e-3


def test_rate_option_replaces_a_missing_time_column(tmp_path: Path, device):
    csv = write(tmp_path / "no_time.csv", device, with_time=False)
    refused = magnet("heading", str(csv))
    assert refused.returncode == 2
    assert "t_s" in refused.stderr and "--rate" in refused.stderr and "Traceback" not in refused.stderr
    accepted = magnet("heading", str(csv), "--rate", str(RATE_HZ))
    assert accepted.returncode == 0, accepted.stderr
    with_time = magnet("heading", str(write(tmp_path / "timed.csv", device)))
    np.testing.assert_allclose(
        read_output(accepted.stdout)["heading_deg"], read_output(with_time.stdout)["heading_deg"], atol=0.05
    )


def test_without_gyroscope_tilt_stays_and_offline_is_refused(tmp_path: Path, device):
    csv = write(tmp_path / "tilt.csv", device, with_gyro=False)
    result = magnet("heading", str(csv))
    assert result.returncode == 0, result.stderr
    out = read_output(result.stdout)
    assert not np.any(out["flags"].astype(int) & HeadingFlag.FUSED)
    quat = np.column_stack([out[k] for k in ("qw", "qx", "qy", "qz")])
    heading, pitch, _ = frames.quaternion_to_euler(quat)
    assert np.abs(angle_difference_deg(heading, out["heading_deg"])).max() < 1e-3
    assert np.abs(pitch - out["pitch_deg"]).max() < 1e-3
    refused = magnet("heading", str(csv), "--offline")
    assert refused.returncode == 2 and "gx,gy,gz" in refused.stderr


def test_fit_with_a_gyroscope_needs_times_and_beats_the_calibration_in_force(tmp_path: Path, device):
    gyr, acc, mag, _ = device
    raw = mag @ np.diag([1.1, 0.9, 1.0]).T + [20.0, -10.0, 5.0]
    csv = write(tmp_path / "iron.csv", (gyr, acc, raw, None), with_time=False)
    refused = magnet("fit", str(csv), "--method", "ellipsoid")
    assert refused.returncode == 2 and "t_s" in refused.stderr and "--rate" in refused.stderr
    cal = tmp_path / "cal.json"
    accepted = magnet("fit", str(csv), "--method", "ellipsoid", "--rate", str(RATE_HZ), "--out", str(cal))
    assert accepted.returncode == 0, accepted.stderr
    again = magnet("fit", str(csv), "--method", "sphere", "--rate", str(RATE_HZ), "--in-force", str(cal))
    assert again.returncode == 1 and "more constant than the calibration in force" in again.stderr
