"""The history of a device with no records (issue 32: the dashboard answered 504 after its 5 s query timeout, as the
calibrator answered history only for devices with a record in force). A real calibrator now answers a device asked
by name with an empty history and a message at once; the dashboard says 404 with that message, ``magnet get
calibration DEV --history`` exits 1 naming the device."""

from __future__ import annotations

import json
import time
import warnings

import pytest
import zenoh
from helpers import NO_SCOUT, connect_args, free_ports, listen_args, run_magnet, wait_for
from test_dashboard_app import TOKEN, FakeControl

from services.dashboard.app import create_app
from services.dashboard.ingest import Control
from services.dashboard.state import FleetState

with warnings.catch_warnings():
    warnings.filterwarnings("ignore", message=".*httpx.*")
    from starlette.testclient import TestClient


def _session(port: int) -> zenoh.Session:
    conf = zenoh.Config()
    conf.insert_json5("connect/endpoints", json.dumps([f"tcp/127.0.0.1:{port}"]))
    conf.insert_json5("scouting/multicast/enabled", "false")
    return zenoh.open(conf)


@pytest.mark.integration
def test_the_history_of_a_device_without_records_is_answered_at_once(procs, tmp_path):
    (cal_port,) = free_ports(1)
    procs.start("calibrator", "calibrator", "--db", str(tmp_path / "c.db"), *listen_args(cal_port))
    with _session(cal_port) as session:
        control = Control(session, "magnet")
        wait_for(lambda: control._ask("magnet/@status/calibrator")[0], 30, "the calibrator's status")
        started = time.monotonic()
        answers, errors = control.history("never-seen", 10)
        took = time.monotonic() - started
        assert errors == [] and answers == [
            {
                "v": 1,
                "device": "never-seen",
                "records": [],
                "changes": [],
                "message": "no calibration is stored for never-seen",
            }
        ]
        assert took < 2.0, f"the calibrator took {took:.1f} s"  # the dashboard's query timeout is 5 s
        state = FleetState(None)
        state.on_alive("never-seen", True)
        client = TestClient(create_app(state, control, TOKEN, view_needs_token=False), base_url="http://127.0.0.1")
        reply = client.get("/api/devices/never-seen/history")
        assert reply.status_code == 404 and "no calibration is stored for never-seen" in reply.json()["error"]
        assert list(session.get("magnet/*/calibration/history", timeout=2)) == []  # a wildcard: devices with records
    out = run_magnet("get", "calibration", "never-seen", "--history", *NO_SCOUT, *connect_args(cal_port),
                     "--timeout", "3")  # fmt: skip
    assert out.returncode == 1 and "never-seen" in out.stderr, out.stderr
    assert procs.alive("calibrator")


def test_the_dashboard_answers_404_when_the_calibrator_has_no_record():
    class Empty(FakeControl):
        def history(self, device, limit):
            return [{"device": device, "records": [], "changes": [], "message": "none"}], []

    state = FleetState(None)
    state.on_alive("imu-9", True)
    client = TestClient(create_app(state, Empty(), TOKEN, view_needs_token=False), base_url="http://127.0.0.1")
    reply = client.get("/api/devices/imu-9/history")
    assert reply.status_code == 404 and "no calibration is stored for imu-9" in reply.json()["error"]
