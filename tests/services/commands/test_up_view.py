"""The ``magnet up`` view: drift alerts counted, marked and listed with their advice; waiting devices without
question-mark bars; notes shortened at word boundaries; redrawn in place on a terminal (rich Live, no screen clear)."""

import io

from magnet import wire
from magnet.drift import Alert, AlertKind
from magnet.drift.alerts import advice_for
from services.commands.up_view import DeviceView, Viewer, render_lines

#: the advice shown is the fixed table's for the cause, whatever text the message carried
ADVICE = advice_for(AlertKind.FIELD_STRENGTH, 50.1)


def alert(cleared=False):
    return Alert("dev-001", AlertKind.FIELD_STRENGTH, 5_000_000_000, 58.24, 50.1, "a peer's own words", cleared)


def test_an_alert_is_counted_marks_the_device_and_its_advice_is_listed_whole():
    viewer = Viewer("magnet", io.StringIO(), tty=False)
    viewer.feed(wire.Kind.CALIBRATION, wire.pack({"device": "dev-001", "id": "abc", "quality": {}}))
    viewer.feed(wire.Kind.ALERT, wire.pack(alert().to_message()))
    viewer.feed(wire.Kind.ALERT, b"\x93garbage")  # skipped
    lines = render_lines(viewer.views, 12.0, width=80)
    assert "1 calibrated, 1 alert(s)" in lines[0]
    row = next(i for i, line in enumerate(lines) if line.startswith("dev-001"))
    assert " drifted " in lines[row] and lines[row + 1] == "  ALERT field strength 58.2 uT (expected 50.1 uT)"
    assert all(len(line) <= 80 for line in lines), lines  # the whole view fits 80 columns
    listed = " ".join(line.strip() for line in lines if line.startswith(("ALERT", "    ")))
    assert listed == f"ALERT dev-001: field strength 58.2 uT (expected 50.1 uT): {ADVICE}"
    assert all(len(line) <= 80 for line in lines[2 + len(viewer.views) :])
    viewer.feed(wire.Kind.ALERT, wire.pack(alert(cleared=True).to_message()))
    lines = render_lines(viewer.views, 13.0)
    assert "0 alert(s)" in lines[0] and " calibrated " in lines[2] and not any("ALERT" in line for line in lines)


def test_waiting_devices_have_no_question_marks_and_notes_end_on_a_word():
    views = {
        "dev-000": DeviceView(),
        "dev-001": DeviceView(state="collecting", coverage=0.4, missing=("turn it upside down slowly",) * 4),
    }
    lines = render_lines(views, 1.0)
    assert "?" not in "\n".join(lines) and "waiting for samples" in lines[2]
    note = lines[4].strip()  # under dev-001's row
    assert note.endswith("...") and len(note) <= 76
    assert note[:-4].rstrip(",").endswith("slowly") or note[:-4].endswith(("turn", "it", "upside", "down"))


def test_a_terminal_view_is_redrawn_in_place_without_clearing_the_screen():
    out = io.StringIO()
    viewer = Viewer("magnet", out, tty=True)
    viewer.views["dev-000"] = DeviceView()
    viewer.show(1.0)
    viewer.show(2.0)
    viewer.close()
    text = out.getvalue()
    assert "\x1b[2J" not in text  # no full-screen clear (the flicker)
    assert "magnet up: 1 device(s)" in text and "2.0 s" in text


def test_the_view_says_its_heading_is_true_and_what_err_and_resid_are():
    lines = render_lines({"dev-000": DeviceView(state="calibrated", true_heading_deg=123.4, error_deg=0.3)}, 1.0)
    legend = " ".join(lines[-2:])
    assert "hdg: true heading" in legend and "err: hdg minus the simulator's true heading" in legend
    assert "resid: the calibration's residual, uT" in legend and all(len(line) <= 80 for line in lines)
