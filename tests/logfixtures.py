"""Flight logs for the tests: the real ones in data/, and a MAVLink telemetry log written with pymavlink's own
encoder from the simulator's truth (as MAVProxy records one: each message after its 8-byte big-endian time in us)."""

from __future__ import annotations

import struct
from pathlib import Path

import numpy as np

from magnet.simulator.errors import SensorErrors
from magnet.simulator.run import SimulatedRun, SimulatorConfig, simulate
from magnet.units import STANDARD_GRAVITY_MS2

DATA = Path(__file__).resolve().parents[1] / "data"
PX4_LOG = DATA / "px4_pyulog_sample.ulg"
ARDUPILOT_LOG = DATA / "ardupilot_pymavlink_test.bin"

HARD_IRON_UT = (20.0, -15.0, 30.0)
SOFT_IRON = ((1.1, 0.05, 0.02), (0.05, 0.95, -0.03), (0.02, -0.03, 1.02))


def simulated_run(count: int = 1500, rate_hz: float = 50.0, trajectory: str = "tumble") -> SimulatedRun:
    errors = SensorErrors(hard_iron_ut=HARD_IRON_UT, soft_iron=SOFT_IRON, noise_ut=0.1)
    return simulate(SimulatorConfig(trajectory=trajectory, count=count, rate_hz=rate_hz, errors=errors, seed=3))


def write_tlog(
    path: Path, run: SimulatedRun, *, with_imu: bool = True, boot_ms: int = 5000, count: int | None = None
) -> None:
    """A telemetry log of ``run``: SCALED_IMU2 (instance 1) and RAW_IMU (instance 0, in ArduPilot's scaling) with
    the measured field, ATTITUDE with the true attitude, SYS_STATUS (current 12.5 A) and VFR_HUD (throttle 40 %);
    the first ``count`` samples (default all)."""
    from pymavlink import mavutil

    log = mavutil.mavlogfile(str(path), write=True, source_system=7)
    try:
        for k in range(len(run.t_s) if count is None else count):
            t_ms = boot_ms + int(np.rint(run.t_s[k] * 1000))
            stamp = struct.pack(">Q", 1_700_000_000_000_000 + t_ms * 1000)
            mag_mg = np.round(run.mag_ut[k] * 10).astype(int)
            acc_mg = np.round(run.acc_ms2[k] / STANDARD_GRAVITY_MS2 * 1000).astype(int)
            gyr = np.round(run.gyr_rads[k] * 1000).astype(int)
            messages = []
            if with_imu:
                messages.append(log.mav.scaled_imu2_encode(t_ms, *acc_mg, *gyr, *mag_mg))
                messages.append(log.mav.raw_imu_encode(t_ms * 1000, *acc_mg, *gyr, *mag_mg))
            yaw, pitch, roll = (np.radians(a[k]) for a in (run.heading_deg, run.pitch_deg, run.roll_deg))
            yaw = (yaw + np.pi) % (2 * np.pi) - np.pi
            messages.append(log.mav.attitude_encode(t_ms, roll, pitch, yaw, 0.0, 0.0, 0.0))
            if k % 10 == 0:
                messages.append(log.mav.sys_status_encode(0, 0, 0, 500, 12000, 1250, 80, 0, 0, 0, 0, 0, 0))
                messages.append(log.mav.vfr_hud_encode(0.0, 0.0, int(run.heading_deg[k]), 40, 10.0, 0.0))
            for message in messages:
                log.write(stamp + message.pack(log.mav))
    finally:
        log.close()
