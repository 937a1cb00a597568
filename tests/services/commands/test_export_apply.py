"""``apply_params`` (``magnet export --apply``) against the pymavlink vehicle stand-in (tests/mav_vehicle.py): every
parameter set and read back, old -> new reported; refused while the vehicle is armed, nothing changed."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from helpers import REPO_ROOT, free_ports

from services.commands.export_apply import ApplyError, apply_params

pytestmark = pytest.mark.integration

sys.path.insert(0, str(REPO_ROOT / "tests"))
from mav_vehicle import PARAMETERS  # noqa: E402

WANTED = {
    "COMPASS_OFS_X": -25.5,
    "COMPASS_OFS_Y": 12.25,
    "COMPASS_OFS_Z": -9.0,
    "COMPASS_DIA_X": 0.93,
    "COMPASS_DIA_Y": 1.05,
    "COMPASS_DIA_Z": 1.0,
    "COMPASS_ODI_X": -0.03,
    "COMPASS_ODI_Y": 0.0,
    "COMPASS_ODI_Z": -0.02,
    "COMPASS_MOTCT": 2.0,
    "COMPASS_MOT_X": -1.5,
    "COMPASS_MOT_Y": 1.0,
    "COMPASS_MOT_Z": -2.0,
}


def stand_in(tmp_path: Path, port: int, *args: str) -> subprocess.Popen[bytes]:
    # -P: not tests/ first on its path, where tests/magnet/ would stand for the magnet package
    command = [sys.executable, "-P", str(REPO_ROOT / "tests" / "mav_vehicle.py"), "--url", f"udpout:127.0.0.1:{port}"]
    extra = ["--rate", "0", "--duration", "30", "--truth", str(tmp_path / "vehicle.npz"), *args]
    return subprocess.Popen([*command, *extra], cwd=REPO_ROOT)


def final_params(proc: subprocess.Popen[bytes], tmp_path: Path) -> dict[str, float]:
    proc.terminate()
    assert proc.wait(timeout=10) == 0
    values = np.load(tmp_path / "vehicle.npz")["params"]
    return dict(zip(PARAMETERS, values.tolist()))


def test_apply_sets_and_reads_back_every_parameter(tmp_path: Path) -> None:
    [port] = free_ports(1)
    proc = stand_in(tmp_path, port)
    try:
        report = apply_params(f"udpin:127.0.0.1:{port}", WANTED)
    finally:
        held = final_params(proc, tmp_path)
    assert report.sysid == 1 and [c.name for c in report.changes] == list(WANTED)
    for change in report.changes:
        assert change.old == PARAMETERS[change.name]
        assert np.float32(change.read_back) == np.float32(WANTED[change.name])
        assert np.float32(held[change.name]) == np.float32(WANTED[change.name])
    assert "COMPASS_OFS_X: 0 -> -25.5" in report.lines() and "COMPASS_DIA_Z: 1 (unchanged)" in report.lines()
    assert report.to_dict()["unchanged"] == ["COMPASS_DIA_Z", "COMPASS_ODI_Y"]


def test_apply_is_refused_while_the_vehicle_is_armed_and_changes_nothing(tmp_path: Path) -> None:
    [port] = free_ports(1)
    proc = stand_in(tmp_path, port, "--armed")
    try:
        with pytest.raises(ApplyError, match="armed"):
            apply_params(f"udpin:127.0.0.1:{port}", WANTED)
    finally:
        held = final_params(proc, tmp_path)
    assert held == PARAMETERS


def test_apply_names_what_is_wrong(tmp_path: Path) -> None:
    [port] = free_ports(1)
    with pytest.raises(ApplyError, match="no vehicle"):
        apply_params(f"udpin:127.0.0.1:{port}", {"COMPASS_OFS_X": 1.0})
    with pytest.raises(ApplyError, match=r"1\.\.16"):
        apply_params(f"udpin:127.0.0.1:{port}", {"A_NAME_FAR_TOO_LONG_X": 1.0})
    proc = stand_in(tmp_path, port)
    try:
        with pytest.raises(ApplyError, match="NO_SUCH_PARAM"):
            apply_params(f"udpin:127.0.0.1:{port}", {"NO_SUCH_PARAM": 1.0})
    finally:
        final_params(proc, tmp_path)


def test_export_apply_from_the_command_line(tmp_path: Path) -> None:
    """``magnet export --calibration cal.json --format ardupilot --apply URL``: the vehicle ends up holding the
    exported parameters, and the command says what changed."""
    import json

    from helpers import run_magnet

    cal = {"method": "ellipsoid", "offset": [12.0, -3.5, 7.25], "matrix": [[1.02, 0.01, 0], [0.01, 0.97, 0], [0, 0, 1]]}
    (tmp_path / "cal.json").write_text(json.dumps(cal))
    [port] = free_ports(1)
    proc = stand_in(tmp_path, port)
    try:
        args = ["export", "--calibration", str(tmp_path / "cal.json"), "--format", "ardupilot"]
        result = run_magnet(*args, "--apply", f"udpin:127.0.0.1:{port}", timeout=30)
    finally:
        held = final_params(proc, tmp_path)
    assert result.returncode == 0, result.stderr
    assert "vehicle 1" in result.stdout and "COMPASS_OFS_X: 0 -> -120" in result.stdout
    assert np.float32(held["COMPASS_OFS_X"]) == np.float32(-120.0)
    assert np.float32(held["COMPASS_DIA_Y"]) != np.float32(1.0)


def refused(tmp_path: Path, *args: str, match: str) -> tuple[str, dict[str, float]]:
    """Apply ``WANTED`` to a stand-in run with ``args``: the ApplyError's message (matching ``match``) and the
    parameters the vehicle holds at the end."""
    [port] = free_ports(1)
    proc = stand_in(tmp_path, port, *args)
    try:
        with pytest.raises(ApplyError, match=match) as error:
            apply_params(f"udpin:127.0.0.1:{port}", WANTED)
    finally:
        held = final_params(proc, tmp_path)
    return str(error.value), held


def test_a_value_never_confirmed_restores_everything_written(tmp_path: Path) -> None:
    """Issue 32: the offsets were left new and the rest old. Now all four written are set back and named."""
    message, held = refused(tmp_path, "--no-confirm", "COMPASS_DIA_X", match="did not take COMPASS_DIA_X")
    assert "no PARAM_VALUE" in message and "NOT restored" not in message
    assert "restored to their old values: COMPASS_OFS_X, COMPASS_OFS_Y, COMPASS_OFS_Z, COMPASS_DIA_X" in message
    assert held == PARAMETERS


def test_another_value_confirmed_restores_everything_written(tmp_path: Path) -> None:
    message, held = refused(tmp_path, "--clamp", "COMPASS_OFS_Y=10", match="did not take COMPASS_OFS_Y = 12.25")
    assert "it read back 10" in message and "restored to their old values: COMPASS_OFS_X, COMPASS_OFS_Y" in message
    assert held == PARAMETERS


def test_a_value_that_cannot_be_restored_is_named(tmp_path: Path) -> None:
    """COMPASS_DIA_X takes 0.93 but holds at most 0.95 after: its old 1 cannot be put back, and the error says so."""
    clamps = ("--clamp", "COMPASS_DIA_X=0.95", "--clamp", "COMPASS_DIA_Y=1")
    message, held = refused(tmp_path, *clamps, match="did not take COMPASS_DIA_Y")
    assert "restored to their old values: COMPASS_OFS_X, COMPASS_OFS_Y, COMPASS_OFS_Z, COMPASS_DIA_Y" in message
    assert message.endswith("NOT restored (check them on the vehicle): COMPASS_DIA_X (was 1)")
    assert np.float32(held["COMPASS_DIA_X"]) == np.float32(0.95) and held["COMPASS_OFS_X"] == 0.0


@pytest.mark.parametrize("sets", [5, len(WANTED)])
def test_arming_partway_stops_and_restores(tmp_path: Path, sets: int) -> None:
    """Issue 32: armed after some writes, the rest went on (7 of 10 written while armed). Now it stops at once and
    sets back what it wrote; armed just after the last write, the HEARTBEAT checked after the writes catches it."""
    message, held = refused(tmp_path, "--arm-after-sets", str(sets), match="armed (partway|during the writes)")
    assert "restored to their old values: COMPASS_OFS_X" in message and "NOT restored" not in message
    assert held == PARAMETERS
    if sets < len(WANTED):  # stopped at the next write (or the one after: the HEARTBEAT may come just after its answer)
        assert "armed partway, before" in message, message
        restored = message.split("restored to their old values: ")[1].split(", ")
        assert sets <= len(restored) <= sets + 1, message


def test_a_disarmed_camera_does_not_speak_for_an_armed_autopilot(tmp_path: Path) -> None:
    """Issue 32: a camera on the same system id sending "disarmed" heartbeats let every write through."""
    message, held = refused(tmp_path, "--armed", "--camera", match="is armed")
    assert message.startswith("vehicle 1 is armed") and held == PARAMETERS
