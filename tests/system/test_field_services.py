"""Calibration in the field through the services (issue 26): a simulated phone walk (texting, raw magnetometer with
hard iron 6-15 times the field) replayed by ``magnet edge --replay`` through a calibrator and a compass on
loopback. It gets a record within its first minute of samples (the compass's headings name it), the record is in
``magnet get history DEV``, and when the phone's hard iron changes mid-walk the calibrator refreshes it in service
(``--recalibrate auto``, the default), which the history marks."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from helpers import connect_args, magnet_json
from motion_pipeline import Pipeline, joined, received

from magnet.simulator import HardIronChange, SensorErrors, SimulatorConfig, Trajectory, simulate

pytestmark = pytest.mark.integration

RATE_HZ, SECONDS, CHANGE_S = 50.0, 110.0, 45.0
BATCH, SPEED = 25, 10.0
LAT, LON, DATE = 50.45, 30.52, "2026-01-01"


def _walk_csv(path: Path) -> np.ndarray:
    """The walk as a ``magnet edge --replay`` CSV; its sample times (N,) s."""
    rng = np.random.default_rng([7, 26])
    errors = SensorErrors.phone(rng, 50.0)
    run = simulate(
        SimulatorConfig(
            trajectory=Trajectory.WALK_TEXTING,
            lat_deg=LAT,
            lon_deg=LON,
            date=DATE,
            rate_hz=RATE_HZ,
            count=int(SECONDS * RATE_HZ),
            errors=errors,
            seed=7,
            hard_iron_change=HardIronChange(CHANGE_S, SensorErrors.phone(rng, 50.0).hard_iron_ut),
        )
    )
    table = np.column_stack([run.t_s, run.mag_ut, run.acc_ms2, run.gyr_rads])
    np.savetxt(path, table, delimiter=",", header="t_s,mx,my,mz,ax,ay,az,gx,gy,gz", comments="", fmt="%.6f")
    return run.t_s


def test_a_phone_walk_is_calibrated_within_a_minute_and_refreshed_in_service_after_its_iron_changes(procs, tmp_path):
    t_s = _walk_csv(tmp_path / "walk.csv")
    place = ["--location", f"{LAT},{LON}"]
    pipeline = Pipeline(procs, tmp_path, place, [*place, "--date", DATE])
    with pipeline.headings() as headings:
        pipeline.replay(tmp_path / "walk.csv", "phone-1", SPEED, BATCH)
        rows = received(headings, "phone-1", len(t_s), BATCH, timeout_s=60)
        ids = joined(headings, "phone-1", "calibration_id")
    calibrated = np.flatnonzero(ids != "")
    assert calibrated.size, f"no record in force; calibrator log:\n{procs.log('calibrator')}"
    assert t_s[rows[calibrated[0]]] <= 60.0, "the first record came after the walk's first minute"
    status, [history] = magnet_json("get", "history", "phone-1", "--json", *connect_args(pipeline.cal_port))
    assert status == 0
    changes = history["changes"]
    assert changes[-1]["action"] == "auto"  # the first record, newest first
    refreshed = [c for c in changes if c.get("in_service")]
    assert refreshed and refreshed[0]["action"] == "refresh", f"no refresh; log:\n{procs.log('calibrator')}"
    # a refresh made after the change is in force at the end, and the compass applied it
    assert ids[-1] == history["records"][0]["id"]
    assert t_s[rows[np.flatnonzero(ids == ids[-1])[0]]] > CHANGE_S
