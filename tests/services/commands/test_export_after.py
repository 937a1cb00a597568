"""``magnet export --apply URL`` then ``--reboot`` and the check (issue 27, items 5 and 7), against the pymavlink
stand-in vehicle (tests/mav_vehicle.py), which corrects the field it sends with its compass parameters as ArduPilot
does: the record of its first compass applied, the autopilot rebooted, and the next seconds of its own field found to
agree with the record; a vehicle that held an older calibration found to disagree (exit 3); a record of another sensor
refused before anything is written; a reboot refused while armed."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np
import pytest
from helpers import REPO_ROOT, free_ports, run_magnet
from test_export_apply import final_params, stand_in

from magnet.model import Calibration
from services.commands.export_after import after_apply
from services.commands.export_apply import ApplyError

pytestmark = pytest.mark.integration

sys.path.insert(0, str(REPO_ROOT / "tests"))
from mav_vehicle import COMPASSES, PARAMETERS, SENSOR_IDS  # noqa: E402

EARTH_UT = 51.006  # the simulator's field at the stand-in's place


def record(tmp_path: Path, sensor: int) -> Path:
    """The true calibration of the stand-in's first compass (its hard and soft iron), naming ``sensor``."""
    errors = COMPASSES[0]
    matrix = np.linalg.inv(np.asarray(errors.distortion))
    cal = Calibration("manual", np.asarray(errors.hard_iron_ut), matrix, EARTH_UT, hardware_id=sensor)
    path = tmp_path / "cal.json"
    path.write_text(json.dumps(cal.to_dict()))
    return path


def export(tmp_path: Path, port: int, *extra: str, sensor: int = SENSOR_IDS[0]):
    args = ["export", "--calibration", str(record(tmp_path, sensor)), "--format", "ardupilot", "--instance", "0"]
    return run_magnet(*args, "--apply", f"udpin:127.0.0.1:{port}", *extra, timeout=60)


def test_applied_rebooted_and_the_vehicle_now_agrees(tmp_path: Path) -> None:
    [port] = free_ports(1)
    proc = stand_in(tmp_path, port, "--rate", "50")
    try:
        result = export(tmp_path, port, "--reboot", "--check-s", "6")
    finally:
        held = final_params(proc, tmp_path)
    print(result.stdout, result.stderr)
    assert result.returncode == 0, result.stderr
    assert "COMPASS_DEV_ID" not in result.stdout.split("watching")[0], "the id is checked, never written"
    assert "magnet export: autopilot rebooted" in result.stdout
    assert "magnet export: check: agrees over" in result.stdout
    assert int(np.load(tmp_path / "vehicle.npz")["reboots"]) == 1
    assert held["COMPASS_OFS_X"] != 0.0 and held["COMPASS_DEV_ID"] == PARAMETERS["COMPASS_DEV_ID"]


def test_a_vehicle_that_held_an_older_calibration_disagrees_and_says_why(tmp_path: Path) -> None:
    [port] = free_ports(1)
    proc = stand_in(tmp_path, port, "--rate", "50", "--param", "COMPASS_OFS_X=80", "--param", "COMPASS_OFS_Y=-60")
    try:
        result = export(tmp_path, port, "--check-s", "5")
    finally:
        final_params(proc, tmp_path)
    print(result.stdout, result.stderr)
    assert result.returncode == 3, result.stderr
    assert "reboot the autopilot before flying" in result.stdout
    assert "check: DISAGREES" in result.stdout and "held a calibration before" in result.stdout


def test_a_record_of_another_sensor_is_refused_and_nothing_written(tmp_path: Path) -> None:
    [port] = free_ports(1)
    proc = stand_in(tmp_path, port)
    try:
        result = export(tmp_path, port, sensor=SENSOR_IDS[1])
    finally:
        held = final_params(proc, tmp_path)
    assert result.returncode == 2
    assert "COMPASS_DEV_ID is 466441 (I2C bus 1 address 0x1e devtype 0x07)" in result.stderr
    assert "fitted for 131874" in result.stderr and "would land on another compass" in result.stderr
    assert held == PARAMETERS


def test_a_reboot_is_refused_while_armed(tmp_path: Path) -> None:
    [port] = free_ports(1)
    proc = stand_in(tmp_path, port, "--armed")
    cal = Calibration("manual", np.zeros(3), np.eye(3))
    try:
        with pytest.raises(ApplyError, match="is armed: not rebooted"):
            after_apply(f"udpin:127.0.0.1:{port}", 57600, 1, cal, 0, {}, {}, do_reboot=True, check_s=0)
    finally:
        final_params(proc, tmp_path)
    assert int(np.load(tmp_path / "vehicle.npz")["reboots"]) == 0
