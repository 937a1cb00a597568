"""Fleet operations end to end, each service in its own process on loopback (explicit ports, no multicast):

- ``magnet get fleet`` over 1,000 stored devices answers in one reply, quickly (the figure: ``magnet bench fleet``);
- a device whose calibration no longer fits its iron raises a drift alert at the compass, the calibrator's fleet
  answer shows it, a rollback to the calibration that fits clears it, and the history shows the rollback.
"""

from __future__ import annotations

import json
import time

import numpy as np
import pytest
import zenoh
from helpers import NO_SCOUT, connect_args, free_ports, listen_args, magnet_json, wait_for

from magnet import wire
from magnet.model import Calibration, Quality
from services.bench.fleet_query import ask_fleet, fill_store, fleet_file, session_config, wait_for_fleet
from services.calibrator.store import CalibrationStore

pytestmark = pytest.mark.integration

HARD_IRON = np.array([40.0, -20.0, 10.0])
LOCATION = "50.45,30.52"


def test_get_fleet_over_a_thousand_devices_answers_in_one_quick_reply(procs, tmp_path):
    names = fill_store(tmp_path / "fleet.db", 1000)
    port = free_ports(1)[0]
    procs.start(
        "calibrator",
        "calibrator",
        "--db",
        str(tmp_path / "fleet.db"),
        "--fleet",
        str(fleet_file(tmp_path / "fleet.json5", names)),
        *listen_args(port),
    )
    with zenoh.open(session_config(port)) as session:
        wait_for_fleet(session, 1000)
        times, replies = zip(*(ask_fleet(session) for _ in range(3)))
    print(f"fleet query over 1000 devices: {min(times) * 1000:.0f} ms fastest of 3")
    assert min(times) < 1.0
    reply = replies[-1]
    assert reply["count"] == 1000 and [d["device"] for d in reply["devices"]] == names
    entry = reply["devices"][7]
    assert entry["state"] == "calibrated" and entry["method"] == "ellipsoid" and entry["location_source"] == "fleet"
    assert entry["location"] == [-60 + 49, -180 + 91, 7] and entry["notes"] == "unit 7"
    assert entry["quality"]["residual_rms_ut"] == 0.3 and entry["alerts"] == []
    code, lines = magnet_json("get", "fleet", *NO_SCOUT, *connect_args(port), "--timeout", "10")
    assert code == 0 and lines[0]["count"] == 1000


def store_two_calibrations(path, device):
    """The calibration that fits HARD_IRON, then one that does not (in force): (right id, wrong id)."""
    quality = Quality(residual_rms_ut=0.3, coverage=0.95)
    right = Calibration("ellipsoid", HARD_IRON, np.eye(3), field_strength=51.0, quality=quality, accepted=True)
    wrong = Calibration(
        "ellipsoid", HARD_IRON + [18.0, 0.0, -9.0], np.eye(3), field_strength=51.0, quality=quality, accepted=True
    )
    now = time.time_ns()
    with CalibrationStore(path) as store:
        for n, cal in enumerate((right, wrong)):
            store.save(wire.DeviceCalibration(device, now + n, cal))
    return right.content_id, wrong.content_id


def fleet_entry(port, device):
    code, lines = magnet_json("get", "fleet", *NO_SCOUT, *connect_args(port), "--timeout", "3")
    if code != 0 or not lines:
        return None
    return next((d for d in lines[0]["devices"] if d["device"] == device), None)


def test_a_drifted_device_raises_an_alert_the_fleet_shows_and_a_rollback_clears_it(procs, tmp_path):
    right_id, wrong_id = store_two_calibrations(tmp_path / "cal.db", "drifty")
    cal_port, comp_port, edge_port = free_ports(3)
    procs.start("calibrator", "calibrator", "--db", str(tmp_path / "cal.db"), *listen_args(cal_port))
    procs.start(
        "compass",
        "compass",
        "--location",
        LOCATION,
        "--drift-window",
        "1",
        "--drift-windows",
        "2",
        *listen_args(comp_port),
        *connect_args(cal_port),
    )
    procs.start(
        "edge",
        "edge",
        "--device",
        "drifty",
        "--emulate",
        "--rate",
        "100",
        "--batch",
        "10",
        "--hard-iron",
        ",".join(map(str, HARD_IRON)),
        "--location",
        LOCATION,
        *listen_args(edge_port),
        *connect_args(cal_port, comp_port),
    )
    remote = [*NO_SCOUT, *connect_args(cal_port)]
    raised = wait_for(
        lambda: (e := fleet_entry(cal_port, "drifty")) and e["alerts"] and e,
        60,
        "the drift alert to reach the calibrator's fleet answer",
    )
    kinds = {a["kind"] for a in raised["alerts"]}
    assert "field_strength" in kinds and raised["calibration_id"] == wrong_id, raised
    alert = next(a for a in raised["alerts"] if a["kind"] == "field_strength")
    assert set(alert) == {"v", "device", "kind", "since_ns", "measured", "expected", "advice"}
    assert alert["expected"] == 51.0 and abs(alert["measured"] - 51.0) > 3
    assert raised["location"] == [50.45, 30.52, 0.0] and raised["location_source"] == "reported"
    code, [rolled] = magnet_json("calibrate", "drifty", "rollback", *remote)
    assert code == 0 and rolled["ok"] and rolled["calibration"]["id"] == right_id, rolled
    cleared = wait_for(
        lambda: (e := fleet_entry(cal_port, "drifty")) and not e["alerts"] and e,
        30,
        "the alert to clear once the right calibration is back in force",
    )
    assert cleared["calibration_id"] == right_id
    code, [history] = magnet_json("get", "calibration", "drifty", "--history", *remote)
    assert [r["id"] for r in history["records"]] == [right_id, wrong_id, right_id]
    change = history["changes"][0]
    assert change["action"] == "rollback" and change["from_id"] == wrong_id and "@" in change["by"]
    time.sleep(3)  # three more windows: the right calibration raises nothing
    assert fleet_entry(cal_port, "drifty")["alerts"] == []
    assert procs.alive("calibrator") and procs.alive("compass") and procs.alive("edge")
    print(json.dumps(alert))
