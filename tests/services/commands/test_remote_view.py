"""How the remote tools print: exactly today's JSON with --json or into a pipe; tables with units and sensible
precision on a terminal (fleet with its alerts and advice, a calibration with offset and matrix, history, a session,
watched headings)."""

import argparse
import io
import json
import sys

from rich.console import Console

from services.commands.remote_view import (
    calibrate_table,
    calibration_table,
    fleet_table,
    history_table,
    show,
    watch_line,
)

ALERT = {
    "v": 1,
    "device": "dev-004",
    "kind": "field_strength",
    "since_ns": 1_700_000_000_000_000_000,
    "measured": 58.23456,
    "expected": 51.0,
    "advice": "look for new iron near the sensor, then recalibrate",
}
FLEET = {
    "count": 2,
    "devices": [
        {
            "device": "dev-000",
            "state": "calibrated",
            "method": "ellipsoid",
            "quality": {"residual_rms_ut": 0.30123456789, "coverage": 0.8123},
            "age_s": 4000.2,
            "location": [50.45, 30.52, 0.0],
            "location_source": "reported",
            "alerts": [],
        },
        {"device": "dev-004", "state": "calibrated", "method": "sphere", "quality": None, "alerts": [ALERT]},
    ],
}


def text(renderable, width=160):
    console = Console(file=io.StringIO(), width=width, record=True)
    console.print(renderable)
    return console.export_text()


def test_json_with_the_flag_or_into_a_pipe_is_todays_json_and_a_terminal_gets_a_table(capsys, monkeypatch):
    today = json.dumps(FLEET, sort_keys=True) + "\n"
    show(argparse.Namespace(json=False), FLEET, fleet_table)  # pytest's capture is no terminal
    assert capsys.readouterr().out == today
    monkeypatch.setattr(sys.stdout, "isatty", lambda: True)
    show(argparse.Namespace(json=True), FLEET, fleet_table)
    assert capsys.readouterr().out == today
    show(argparse.Namespace(json=False), FLEET, fleet_table)
    table = capsys.readouterr().out
    assert "dev-000" in table and "\u2503" in table and not table.lstrip().startswith("{")  # a drawn table


def test_the_fleet_table_has_units_rounded_figures_and_each_alert_with_its_advice():
    out = text(fleet_table(FLEET))
    assert "residual uT" in out and "0.30" in out and "0.3012" not in out and "81 %" in out and "67 min" in out
    assert "50.45, 30.52 (reported)" in out and "calibrated (drift alert)" in out
    assert "dev-004: field strength: 58.2 uT (expected 51.0 uT) - look for new iron near the sensor" in out


def test_a_calibration_shows_offset_and_matrix_and_the_history_its_changes():
    record = {
        "device": "d",
        "id": "abc123",
        "created_ns": 1_700_000_000_000_000_000,
        "method": "ellipsoid",
        "accepted": True,
        "offset": [12.3456, -7.0, 0.5],
        "matrix": [[1.0123456, 0.0, 0.0], [0.0, 0.98, 0.0], [0.0, 0.0, 1.0]],
        "field_strength": 51.04,
        "quality": {"residual_rms_ut": 0.3, "coverage": 0.9},
    }
    out = text(calibration_table(record))
    assert "   12.35    -7.00     0.50 uT" in out and "  1.0123   0.0000   0.0000" in out
    assert "51.04 uT" in out and "90 %" in out
    history = {"device": "d", "records": [record], "changes": [{"action": "rollback", "from_id": "x", "by": "ann"}]}
    out = text(history_table(history))
    assert "abc123" in out and "accepted" in out and "rollback from x by ann" in out
    assert "abc123" in text(calibration_table(history))
    session = {"ok": True, "message": "session started", "progress": {"state": "session", "coverage": 0.42}}
    out = text(calibrate_table(session))
    assert "session started" in out and "42 %" in out and "not yet" in out


def test_watched_headings_and_alerts_read_as_one_line_each():
    heading = {
        "key": "magnet/d/heading",
        "device": "d",
        "seq": 9,
        "true_heading_deg": [10.0, 123.456],
        "heading_deg": [1.0, 114.9],
        "pitch_deg": [0.0, 2.25],
        "roll_deg": [0.0, -3.0],
        "field_ut": [[0, 0, 0], [30.0, 0.0, 40.0]],
    }
    line = text(watch_line(heading))
    assert "true 123.5 deg" in line and "magnetic 114.9 deg" in line and "|B| 50.0 uT" in line
    assert "ALERT field strength: 58.2 uT" in text(watch_line({"key": "k", **ALERT}))


def test_progress_steps_draw_on_a_terminal_only(capsys):
    from services.common.progress import steps

    with steps(["one", "two"], enabled=False) as step:
        step("one")
        step("two")
    assert capsys.readouterr().err == ""
    with steps(["reading", "fitting"], enabled=True) as step:  # rich writes to the (captured) stderr
        step("reading")
        step("fitting")
    assert "fitting" in capsys.readouterr().err


def test_the_vehicle_table_names_each_compass_its_verdict_and_the_parameters_to_set():
    """``magnet get vehicle``: one row per compass, rounded figures with units, the parameters, the summary."""
    from services.commands.remote_view import vehicle_table

    answer = {
        "vehicle": "mav1",
        "summary": "mav1-mag1: rotation (set COMPASS_ORIENT2=2)",
        "compasses": [
            {"device": "mav1-mag0", "verdict": "reference", "angle_deg": 0.0, "rotation_deg": 0.0, "parameters": {}},
            {
                "device": "mav1-mag1",
                "verdict": "rotation",
                "angle_deg": 31.7569,
                "rotation_deg": 89.93,
                "named_rotation": 2,
                "interference_pct": 0.458,
                "residual_ut": 0.598,
                "parameters": {"COMPASS_ORIENT2": 2.0, "CAL_MAG1_ROT": 2.0},
            },
        ],
    }
    out = text(vehicle_table(answer))
    assert "vehicle mav1" in out and "31.8 deg" in out and "90 deg (named 2)" in out and "0.6 uT" in out
    assert "COMPASS_ORIENT2=2, CAL_MAG1_ROT=2" in out and "mav1-mag1: rotation (set COMPASS_ORIENT2=2)" in out


def test_a_calibration_names_the_sensor_it_was_fitted_for_when_it_knows_it():
    record = {"device": "mav1-mag0", "id": "abc", "offset": [0, 0, 0], "matrix": [[1, 0, 0], [0, 1, 0], [0, 0, 1]]}
    assert "sensor" not in text(calibration_table(record))
    out = text(calibration_table({**record, "hardware_id": 466441}))
    assert "sensor" in out and "466441 (I2C bus 1 address 0x1e devtype 0x07)" in out
    assert "33554432" in text(calibration_table({**record, "hardware_id": 1 << 25}))  # another edge's: as it is
