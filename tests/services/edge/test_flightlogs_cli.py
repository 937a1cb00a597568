"""Flight logs through the command line as processes: a telemetry log written by pymavlink replays through ``magnet
edge --replay`` to a Zenoh subscriber; a damaged log is one line on stderr and exit status 2."""

from __future__ import annotations

import subprocess
from pathlib import Path

import numpy as np
import pytest
from helpers import MAGNET, REPO_ROOT, free_ports, listen_args, replay_raw, run_magnet, wait_for
from logfixtures import PX4_LOG, simulated_run, write_tlog

from magnet import wire
from magnet.calibration import FitInput

pytestmark = pytest.mark.integration


def test_a_tlog_replays_through_the_edge(tmp_path: Path) -> None:
    run = simulated_run()
    path = tmp_path / "flight.tlog"
    write_tlog(path, run, count=120)
    batches, _ = replay_raw(path, "drone-1", "--speed", "10", "--batch", "50")
    assert [len(b) for b in batches] == [50, 50, 20]
    mag = np.vstack([b.mag_ut for b in batches])
    assert np.abs(mag - run.mag_ut[:120]).max() < 0.06  # milligauss in the log, float32 on the wire
    assert all(b.gyr_rads is not None and b.acc_ms2 is not None for b in batches)
    t_ns = np.concatenate([b.t_ns for b in batches])
    assert np.array_equal(np.diff(t_ns), np.full(119, 20_000_000))  # the log's 50 Hz


def test_a_damaged_log_is_one_line(tmp_path: Path) -> None:
    cut = tmp_path / "cut.ulg"
    cut.write_bytes(PX4_LOG.read_bytes()[:400])
    out = run_magnet("fit", str(cut), "--method", "ellipsoid", "--out", str(tmp_path / "cal.json"))
    assert out.returncode == 2
    assert out.stderr.strip().count("\n") == 0 and "no logged data" in out.stderr and "Traceback" not in out.stderr
    assert not (tmp_path / "cal.json").exists()


def test_export_asks_the_calibrator_for_the_device(tmp_path: Path) -> None:
    from magnet.calibration import fit
    from services.calibrator.store import CalibrationStore

    run = simulated_run(count=800)
    calibration = fit(FitInput(run.mag_ut, acc=run.acc_ms2, field_ut=50.0), "ellipsoid")
    with CalibrationStore(tmp_path / "c.db") as store:
        store.save(wire.DeviceCalibration("drone-7", 1_700_000_000_000_000_000, calibration))
    port, other = free_ports(2)
    calibrator = subprocess.Popen(
        [*MAGNET, "calibrator", "--db", str(tmp_path / "c.db"), *listen_args(port)], cwd=REPO_ROOT
    )
    try:
        out_file = tmp_path / "drone-7.params"
        args = ["export", "--device", "drone-7", "--format", "px4", "--out", str(out_file), "--timeout", "2"]
        connect = [*listen_args(other), "--connect", f"tcp/127.0.0.1:{port}"]
        out = wait_for(
            lambda: (answer := run_magnet(*args, *connect, timeout=30)).returncode == 0 and answer,
            30,
            "the exported calibration of drone-7",
        )
        assert "CAL_MAG0_ID must already name" in out.stderr
        lines = [line.split("\t") for line in out_file.read_text().splitlines() if not line.startswith("#")]
        values = {name: float(value) for _, _, name, value, _ in lines}
        assert values["CAL_MAG0_XOFF"] == pytest.approx(calibration.offset[0] / 100, abs=1e-6)
        missing = run_magnet("export", "--device", "nobody", "--format", "px4", "--timeout", "1", *connect)
        assert missing.returncode == 1 and "no calibration for nobody" in missing.stderr
    finally:
        calibrator.terminate()
        calibrator.wait(timeout=20)
