"""The dashboard's web side without Zenoh or a browser: pages, JSON, the event stream, and bad input refused with a
clear 4xx that changes nothing (starlette's TestClient, a fake calibrator behind the control)."""

import asyncio
import dataclasses
import functools
import json
import warnings

import numpy as np
import pytest

from magnet import wire
from magnet.attitude.heading import dip_angle_deg
from magnet.drift import Alert, AlertKind
from magnet.earth.geomag import earth_field
from magnet.frames import euler_to_matrix, ned_to_body
from magnet.model import Calibration
from services.dashboard.app import create_app
from services.dashboard.figures import acc_direction, covered_cells, dip_deg
from services.dashboard.service import page_address
from services.dashboard.settings import is_loopback, parse_http
from services.dashboard.state import FleetState

with warnings.catch_warnings():  # starlette >= 1 asks for httpx2, which the package index does not have
    warnings.filterwarnings("ignore", message=".*httpx.*")
    from starlette.testclient import TestClient

TOKEN = "s3cret-token"
GOOD = {"Authorization": f"Bearer {TOKEN}"}


class FakeControl:
    """Records every query; answers like a calibrator (or not at all)."""

    def __init__(self, answers=None, errors=()):
        self.calls = []
        self.answers = answers if answers is not None else [{"v": 1, "ok": True, "message": "session started"}]
        self.errors = list(errors)

    def calibrate(self, device, action, method, to=None, by=None):
        self.calls.append(("calibrate", device, action, method))
        self.extra = (to, by)
        return self.answers, self.errors

    def history(self, device, limit):
        self.calls.append(("history", device, limit))
        return [{"device": device, "records": [{"id": "abc", "method": "ellipsoid"}]}], []


@functools.cache
def _body_field_ut(heading: float, pitch: float, roll: float) -> tuple[float, ...]:
    """The Earth's field at the dashboard's place (uT, body axes) for an attitude: the same for every batch of a
    test, so worked out once (a flood of batches made it again for every one: 70 us a batch)."""
    earth = earth_field(50.45, 30.52, 0.0, "2025-06-01")
    return tuple(np.asarray(ned_to_body(euler_to_matrix(heading, pitch, roll), earth.ned_ut), dtype=float).ravel())


def heading_batch(device="imu-1", seq=7, heading=30.0, pitch=10.0, roll=-5.0, n=5):
    field = np.tile(_body_field_ut(heading, pitch, roll), (n, 1))
    return wire.HeadingBatch(
        device,
        seq,
        np.arange(n, dtype=np.int64),
        np.full(n, heading),
        np.full(n, heading + 8.5),
        np.full(n, pitch),
        np.full(n, roll),
        field,
        8.5,
        "cafe",
        np.ones(n, dtype=np.int64),
    )


@pytest.fixture
def state():
    state = FleetState(earth_field(50.45, 30.52, 0.0, "2025-06-01"))
    state.on_heading(heading_batch())
    state.on_alive("imu-1", True)
    return state


def client_for(state, control, view_needs_token=False):
    app = create_app(state, control, TOKEN, view_needs_token=view_needs_token, operator="ann@lab")
    return TestClient(app, base_url="http://127.0.0.1:8000")


def test_page_static_files_and_plotly_from_the_wheel(state):
    client = client_for(state, FakeControl())
    page = client.get("/")
    assert page.status_code == 200 and "fleet-body" in page.text and "/plotly.min.js" in page.text
    assert "cdn" not in page.text.lower()
    plotly = client.get("/plotly.min.js")
    assert plotly.status_code == 200 and "javascript" in plotly.headers["content-type"]
    assert len(plotly.content) > 1_000_000 and b"plotly" in plotly.content[:2000].lower()
    for name in ("app.js", "dial.js", "style.css"):
        assert client.get(f"/static/{name}").status_code == 200


def test_fleet_and_device_json(state):
    client = client_for(state, FakeControl())
    fleet = client.get("/api/fleet").json()
    [row] = fleet["rows"]
    assert row["device"] == "imu-1" and row["alive"] is True and row["seq"] == 7
    assert row["true_heading_deg"] == pytest.approx(38.5) and row["pitch_deg"] == pytest.approx(10.0)
    assert row["field_ut"] == pytest.approx(state.earth.total_ut, rel=1e-3)
    assert row["dip_deg"] == pytest.approx(state.earth.inclination_deg, abs=0.05)  # dip from pitch/roll and field
    detail = client.get("/api/devices/imu-1").json()
    assert detail["row"]["device"] == "imu-1" and detail["earth"]["total_ut"] > 40
    history = client.get("/api/devices/imu-1/history?limit=5").json()
    assert history["records"][0]["id"] == "abc"


def test_control_with_the_token_reaches_the_calibrator(state):
    control = FakeControl()
    response = client_for(state, control).post(
        "/api/devices/imu-1/calibrate", headers=GOOD, json={"action": "start", "method": "Ellipsoid"}
    )
    assert response.status_code == 200 and response.json()["ok"] is True
    assert control.calls == [("calibrate", "imu-1", "start", "ellipsoid")] and control.extra == (None, "ann@lab")
    rolled = client_for(state, control).post(
        "/api/devices/imu-1/calibrate", headers=GOOD, json={"action": "rollback", "to": "0123abcd0123abcd"}
    )
    assert rolled.status_code == 200 and control.calls[-1][2] == "rollback"
    assert control.extra == ("0123abcd0123abcd", "ann@lab")  # the target and who rolled back
    for body in ({"action": "rollback", "to": "x; action=start"}, {"action": "commit", "to": "0123abcd0123abcd"}):
        refused = client_for(state, control).post("/api/devices/imu-1/calibrate", headers=GOOD, json=body)
        assert refused.status_code == 400 and "calibration id" in refused.json()["error"]
    assert len(control.calls) == 2
    anonymous = client_for(state, control).post("/api/devices/imu-1/calibrate", json={"action": "rollback"})
    assert anonymous.status_code == 401  # rollback needs the token


@pytest.mark.parametrize(
    "headers, path, body, status, words",
    [
        ({}, "/api/devices/imu-1/calibrate", {"action": "start"}, 401, "token"),
        ({"Authorization": "Bearer wrong"}, "/api/devices/imu-1/calibrate", {"action": "start"}, 401, "token"),
        ({"X-Magnet-Token": "wrong"}, "/api/devices/imu-1/calibrate", {"action": "commit"}, 401, "token"),
        (GOOD, "/api/devices/ghost/calibrate", {"action": "start"}, 404, "unknown device"),
        (GOOD, "/api/devices/a$b/calibrate", {"action": "start"}, 400, "may not contain"),
        (GOOD, "/api/devices/imu-1/calibrate", {"action": "erase"}, 400, "action must be one of"),
        (
            GOOD,
            "/api/devices/imu-1/calibrate",
            {"action": "start", "method": "magic"},
            400,
            "unknown calibration method",
        ),
        (GOOD, "/api/devices/imu-1/calibrate", {"action": "start", "method": 3}, 400, "method must be a string"),
        (GOOD, "/api/devices/imu-1/calibrate", ["start"], 400, "JSON object"),
        (GOOD, "/api/devices/imu-1/calibrate", "{not json", 400, "must be JSON"),
        (GOOD, "/api/devices/imu-1/calibrate", "x" * 5000, 413, "larger than"),
    ],
)
def test_bad_control_requests_get_a_clear_4xx_and_change_nothing(state, headers, path, body, status, words):
    control = FakeControl()
    kwargs = {"content": body} if isinstance(body, str) else {"json": body}
    response = client_for(state, control).post(path, headers=headers, **kwargs)
    assert response.status_code == status, response.text
    assert words in response.json()["error"]
    assert control.calls == []  # nothing was asked of the calibrator
    assert not state.knows("ghost")


def test_refusals_of_the_calibrator_and_silence_are_named(state):
    refused = FakeControl(answers=[{"v": 1, "ok": False, "message": "no session to commit: start one first"}])
    response = client_for(state, refused).post("/api/devices/imu-1/calibrate", headers=GOOD, json={"action": "commit"})
    assert response.status_code == 409 and "no session" in response.json()["message"]
    silent = client_for(state, FakeControl(answers=[])).post(
        "/api/devices/imu-1/calibrate", headers=GOOD, json={"action": "status"}
    )
    assert silent.status_code == 504 and "no calibrator answered" in silent.json()["error"]


def test_viewing_needs_no_token_on_loopback_but_does_elsewhere(state):
    assert client_for(state, FakeControl()).get("/api/fleet").status_code == 200
    guarded = client_for(state, FakeControl(), view_needs_token=True)
    assert guarded.get("/api/fleet").status_code == 401
    assert guarded.get("/api/stream").status_code == 401
    assert guarded.get(f"/api/fleet?token={TOKEN}").status_code == 401  # never from the address (issue 32)
    assert guarded.get("/api/fleet", headers={"Authorization": f"Bearer {TOKEN}"}).status_code == 200
    assert guarded.get("/").status_code == 200  # the page itself holds no data


def test_bad_view_requests(state):
    client = client_for(state, FakeControl())
    assert client.get("/api/devices/ghost").status_code == 404
    assert client.get("/api/devices/imu-1/history?limit=lots").status_code == 400
    assert client.get("/api/devices/imu-1/history?limit=0").status_code == 400
    assert client.get("/api/stream?device=a*b").status_code == 400


def test_stream_sends_the_fleet_then_only_changed_rows(state):
    app = create_app(state, FakeControl(), TOKEN, interval_s=0.01)
    dashboard = app.state.dashboard

    async def first_events(count):
        events = []
        stream = dashboard._events("imu-1")
        async for text in stream:
            events.append(text if isinstance(text, str) else bytes(text).decode())  # a fleet event: UTF-8 pieces
            if len(events) == 2:
                state.on_heading(heading_batch(seq=8, heading=90.0))
            if len(events) >= count:
                break
        await stream.aclose()
        return events

    events = asyncio.run(first_events(4))
    parsed = [(e.split("\n")[0][7:], json.loads(e.split("\n")[1][6:])) for e in events]
    assert [name for name, _ in parsed[:2]] == ["fleet", "device"]
    assert [r["seq"] for r in parsed[0][1]["rows"]] == [7]
    fleets = [data for name, data in parsed if name == "fleet"]
    assert [r["seq"] for r in fleets[1]["rows"]] == [8] and fleets[1]["rows"][0]["heading_deg"] == 90.0
    assert state.traces == {} or state.traces["imu-1"].viewers == 0  # the viewer left


def test_state_rows_alerts_and_traces():
    state = FleetState(None)
    state.watch("d1", +1)
    raw = wire.RawBatch(
        "d1",
        1,
        "lsm303dlh",
        np.arange(3),
        np.eye(3) * 40,
        None,
        {"heading_deg": np.full(3, 100.0), "pitch_deg": np.zeros(3), "roll_deg": np.zeros(3)},
    )
    state.on_raw(raw)
    batch = heading_batch("d1", seq=1, heading=92.0)
    state.on_heading(batch)
    row = state.rows["d1"]
    assert row.truth_error_deg == pytest.approx(0.5)  # true heading 100.5 against truth 100
    state.on_progress(
        {
            "device": "d1",
            "state": "session",
            "session": True,
            "method": "ellipsoid",
            "samples": 120,
            "coverage": 0.42,
            "missing": ["turn it upside down"],
            "accepted": False,
            "reason": "more",
        }
    )
    alerts = state.rows["d1"].alerts(0.0, None)
    assert "fit rejected" in alerts
    assert len(state.traces["d1"].raw) == 0  # a new session starts a new cloud
    state.on_raw(raw)
    calibration = Calibration("ellipsoid", np.zeros(3), np.eye(3), quality={"residual_rms_ut": 0.3, "coverage": 0.9})
    state.on_calibration(wire.DeviceCalibration("d1", 5_000_000, calibration))
    row = state.changes(-1)[1][0]
    assert row["state"] == "calibrated" and row["residual_ut"] == 0.3 and row["calibrated_ms"] == 5
    _, changed = state.changes(state.version)
    assert changed == []
    detail = state.detail("d1")
    assert len(detail["raw"]) == 3 and len(detail["calibrated"]) == 5 and len(detail["cells"]) == 100
    state.on_progress({"device": "d1", "state": "session", "session": True})
    state.on_calibration(wire.DeviceCalibration("d1", 5_000_000, calibration))  # asked again: no change
    assert state.rows["d1"].state == "session"


def test_a_drift_alert_shows_with_its_advice_is_counted_and_a_calibrated_device_in_alert_is_not_plain():
    state = FleetState(None)
    calibration = Calibration("ellipsoid", np.zeros(3), np.eye(3), quality={"residual_rms_ut": 0.3, "coverage": 0.9})
    state.on_calibration(wire.DeviceCalibration("d1", 5_000_000, calibration))
    assert state.changes(-1)[1][0]["status"] == "calibrated" and state.summary()["alerts"] == 0
    raised = Alert("d1", AlertKind.FIELD_STRENGTH, 7_000_000_000, 58.2, 50.1, "look for new iron, then recalibrate")
    state.on_alert(raised)
    version = state.version
    state.on_alert(raised)  # asked again: nothing changes
    assert state.version == version
    state.on_alert(dataclasses.replace(raised, kind=AlertKind.CALIBRATION_AGE, measured=400.0, expected=365.0))
    row = state.changes(-1)[1][0]
    assert row["state"] == "calibrated" and row["status"] == "drifted"
    assert row["alerts"][:2] == ["drift: calibration age", "drift: field strength"]
    strength = next(a for a in row["drift"] if a["kind"] == "field_strength")
    assert strength == {
        "kind": "field_strength",
        "since_ms": 7000,
        "measured": 58.2,
        "expected": 50.1,
        "unit": "uT",
        "advice": "look for new iron, then recalibrate",
    }
    assert state.summary()["alerts"] == 2 and state.summary()["in_alert"] == 1
    for kind in (AlertKind.FIELD_STRENGTH, AlertKind.CALIBRATION_AGE):
        state.on_alert(dataclasses.replace(raised, kind=kind, cleared=True))
    assert state.changes(-1)[1][0]["status"] == "calibrated" and state.summary()["alerts"] == 0
    state.on_alert(dataclasses.replace(raised, device="unknown", cleared=True))  # a clear for nobody adds no row
    assert "unknown" not in state.rows


def test_quaternion_optional_field_is_shown_when_present():
    state = FleetState(None)
    state.on_heading(heading_batch("q"), quat_wxyz=[[1, 0, 0, 0]] * 5)
    assert state.changes(-1)[1][0]["quat_wxyz"] == [1.0, 0.0, 0.0, 0.0]
    state.on_heading(heading_batch("q"), quat_wxyz="garbage")
    assert state.changes(-1)[1][0]["quat_wxyz"] is None


def test_helpers():
    assert parse_http("127.0.0.1:8080") == ("127.0.0.1", 8080) and parse_http("[::1]:80") == ("::1", 80)
    for bad in ("8080", ":80", "host:port", "h:70000"):
        with pytest.raises(ValueError, match="--http"):
            parse_http(bad)
    assert is_loopback("127.0.0.1") and is_loopback("::1") and not is_loopback("0.0.0.0")
    assert page_address("127.0.0.1", 80, "t") == "http://127.0.0.1:80/?token=t"
    down = acc_direction(np.array([0.0]), np.array([0.0]))
    assert np.allclose(down, [[0, 0, -1]])
    rng = np.random.default_rng(1)
    for field, pitch, roll in zip(rng.normal(size=(20, 3)) * 40, rng.uniform(-89, 89, 20), rng.uniform(-180, 180, 20)):
        expected = dip_angle_deg(field, acc_direction(pitch, roll))
        assert dip_deg(*field, pitch, roll) == pytest.approx(float(expected), abs=1e-9)
    rng = np.random.default_rng(0)
    sphere = rng.normal(size=(5000, 3))
    assert covered_cells(sphere * 50 + 20).all() and covered_cells(np.zeros((0, 3))).sum() == 0


def test_the_heading_plot_gets_the_last_sixty_seconds_thinned():
    from services.dashboard.figures import HEADING_POINTS, recent_headings

    samples = [(i * 20_000_000, float(i % 360), float((i + 8) % 360)) for i in range(5000)]  # 100 s at 50 Hz
    shown = recent_headings(samples)
    assert shown[-1] == samples[-1] and len(shown) <= HEADING_POINTS
    span_s = (shown[-1][0] - shown[0][0]) / 1e9
    assert 59.0 <= span_s <= 60.0, span_s
    assert recent_headings([]) == [] and recent_headings(samples[:3]) == samples[:3]


def test_a_device_is_judged_against_the_field_where_it_says_it_is():
    state = FleetState(earth_field(50.45, 30.52, 0.0, "2026-06-01"), date="2026-06-01")  # the dashboard's Kyiv
    state.watch("mav1-mag0", +1)
    state.on_heading(heading_batch("mav1-mag0"))
    assert state.detail("mav1-mag0")["earth"]["total_ut"] == pytest.approx(51.1, abs=0.3)
    from magnet.earth.location import Location

    zurich = Location(47.37, 8.54, 400.0)
    raw = wire.RawBatch("mav1-mag0", 2, "mavlink", np.arange(3), np.eye(3) * 40, None, None, location=zurich)
    state.on_raw(raw)
    assert state.detail("mav1-mag0")["earth"]["total_ut"] == pytest.approx(48.4, abs=0.3)
    assert state.detail("mav1-mag0")["earth"]["total_ut"] != state.summary()["earth"]["total_ut"]
    listed = FleetState(state.earth, date="2026-06-01", places={"boat-1": zurich})  # the places file (--fleet)
    listed.watch("boat-1", +1)
    listed.on_heading(heading_batch("boat-1"))
    assert listed.detail("boat-1")["earth"]["total_ut"] == pytest.approx(48.4, abs=0.3)


def test_a_device_whose_headings_stop_is_silent_after_its_own_interval_though_its_token_lives():
    now = [0.0]
    state = FleetState(None, clock=lambda: now[0])
    state.on_alive("mav1-mag0", True)
    for seq in range(5):  # a batch every 2 s
        now[0] = 2.0 * seq
        state.on_heading(heading_batch("mav1-mag0", seq=seq))
    now[0] = 8.0 + 9.0  # 4.5 intervals: still sending as far as anyone can tell
    assert state.changes(-1)[1][0]["alive"] is True and state.summary()["alive"] == 1
    now[0] = 8.0 + 10.5  # more than 5 of its own intervals
    row = state.rows["mav1-mag0"].to_json(now[0], None)
    assert row["alive"] is False and "no headings" in row["alerts"] and state.summary()["alive"] == 0


# ---- issue 32: the browser's front door --------------------------------------------------------------------------


def test_a_host_the_dashboard_was_not_told_of_is_refused(state):
    """DNS rebinding: a page at evil.example whose name now resolves to 127.0.0.1 sends Host: evil.example."""
    client = client_for(state, FakeControl())
    for host in ("evil.example", "evil.example:8000", "127.0.0.1.evil.example"):
        refused = client.get("/api/fleet", headers={"Host": host})
        assert refused.status_code == 403 and "not one this dashboard answers to" in refused.json()["error"]
    for host in ("127.0.0.1:8000", "localhost:8000", "[::1]:8000", "LOCALHOST"):
        assert client.get("/api/fleet", headers={"Host": host}).status_code == 200, host
    told = TestClient(create_app(state, FakeControl(), TOKEN, allowed_hosts=("field-pc",)), base_url="http://field-pc")
    assert told.get("/api/fleet").status_code == 200


def test_a_foreign_origin_is_refused_even_with_the_token(state):
    client = client_for(state, FakeControl())
    foreign = {"Origin": "http://evil.example", **GOOD}
    response = client.post("/api/devices/imu-1/calibrate", headers=foreign, json={"action": "status"})
    assert response.status_code == 403 and "evil.example" in response.json()["error"]
    assert client.get("/api/fleet", headers={"Origin": "http://localhost:3000"}).status_code == 403
    own = {"Origin": "http://127.0.0.1:8000", **GOOD}
    assert client.post("/api/devices/imu-1/calibrate", headers=own, json={"action": "status"}).status_code == 200


def test_the_control_token_is_never_taken_from_the_address(state):
    client = client_for(state, FakeControl())
    response = client.post(f"/api/devices/imu-1/calibrate?token={TOKEN}", json={"action": "status"})
    assert response.status_code == 401


def test_a_large_body_is_refused_by_its_declared_length_before_it_is_read(state):
    client = client_for(state, FakeControl())
    read = []

    def body():
        for _ in range(100):
            read.append(1)
            yield b" " * 65536

    response = client.post(
        "/api/devices/imu-1/calibrate", headers={**GOOD, "Content-Length": str(200 * 1024 * 1024)}, content=body()
    )
    assert response.status_code == 413 and len(read) <= 1


def test_a_stream_for_an_unknown_device_is_refused(state):
    client = client_for(state, FakeControl())
    response = client.get("/api/stream?device=ghost-42")
    assert response.status_code == 404 and "unknown device" in response.json()["error"]


def test_event_streams_are_limited(state, monkeypatch):
    from services.dashboard import app as app_module

    client = client_for(state, FakeControl())
    client.app.state.dashboard.streams = app_module.MAX_STREAMS
    response = client.get("/api/stream")
    assert response.status_code == 503 and "event streams are open already" in response.json()["error"]


def test_a_message_logged_over_and_over_goes_to_the_log_once_per_period_with_its_count():
    import logging

    from services.dashboard.service import OncePer

    now = [0.0]
    once = OncePer(10.0, clock=lambda: now[0])

    def record(msg):
        return logging.LogRecord("uvicorn.error", logging.WARNING, __file__, 1, msg, None, None)

    assert once.filter(record("Exceeded concurrency limit."))
    assert not any(once.filter(record("Exceeded concurrency limit.")) for _ in range(1999))
    assert once.filter(record("another message"))  # each message its own
    now[0] = 10.5
    later = record("Exceeded concurrency limit.")
    assert once.filter(later)
    assert later.getMessage() == "Exceeded concurrency limit. (1999 more like it in the last 10 s)"
