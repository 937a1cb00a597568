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


#: MAG layouts ArduPilot has logged (format characters, columns), as its LogStructure.h defined them over the years
DATAFLASH_MAG_LAYOUTS = {
    "2013": ("Ihhhhhh", "TimeMS,MagX,MagY,MagZ,OfsX,OfsY,OfsZ"),
    "2014": ("Ihhhhhhhhh", "TimeMS,MagX,MagY,MagZ,OfsX,OfsY,OfsZ,MOfsX,MOfsY,MOfsZ"),
    "2016": ("QhhhhhhhhhBI", "TimeUS,MagX,MagY,MagZ,OfsX,OfsY,OfsZ,MOfsX,MOfsY,MOfsZ,Health,S"),
    "2020": ("QBhhhhhhhhhBI", "TimeUS,I,MagX,MagY,MagZ,OfsX,OfsY,OfsZ,MOX,MOY,MOZ,Health,S"),
    "unknown": ("Ihhh", "TimeMS,FldX,FldY,FldZ"),
}
#: the IMU layout of the same years (old logs stamp in ms)
DATAFLASH_IMU_LAYOUTS = {
    "TimeMS": ("Iffffff", "TimeMS,GyrX,GyrY,GyrZ,AccX,AccY,AccZ"),
    "TimeUS": ("QBffffff", "TimeUS,I,GyrX,GyrY,GyrZ,AccX,AccY,AccZ"),
}
DATAFLASH_OFFSETS_MG = (-120, 45, 80)  # the offsets ArduPilot added to the reading (OfsX..Z)
DATAFLASH_MOTOR_MG = (3, -2, 1)  # its motor offsets, where the layout logs them


def _dataflash_record(type_id: int, fmt: str, values: list[object]) -> bytes:
    from pymavlink.DFReader import FORMAT_TO_STRUCT

    layout = "<" + "".join(FORMAT_TO_STRUCT[c][0] for c in fmt)
    return bytes([0xA3, 0x95, type_id]) + struct.pack(layout, *values)


def _dataflash_fmt(type_id: int, name: str, fmt: str, columns: str) -> bytes:
    from pymavlink.DFReader import FORMAT_TO_STRUCT

    length = 3 + struct.calcsize("<" + "".join(FORMAT_TO_STRUCT[c][0] for c in fmt))
    return _dataflash_record(0x80, "BBnNZ", [type_id, length, name.encode(), fmt.encode(), columns.encode()])


def write_dataflash(path: Path, run: SimulatedRun, layout: str) -> None:
    """An ArduPilot DataFlash log of ``run`` whose MAG records have ``DATAFLASH_MAG_LAYOUTS[layout]``, packed with
    pymavlink's DataFlash format characters: FMT records, then per sample a MAG (the reading plus
    ``DATAFLASH_OFFSETS_MG`` plus the motor offsets where logged, milligauss, as ArduPilot logs its corrected field)
    and an IMU record (ms or us as the layout's time)."""
    mag_fmt, mag_cols = DATAFLASH_MAG_LAYOUTS[layout]
    time_field = mag_cols.split(",")[0]
    imu_fmt, imu_cols = DATAFLASH_IMU_LAYOUTS[time_field]
    out = [_dataflash_fmt(0x80, "FMT", "BBnNZ", "Type,Length,Name,Format,Columns")]
    out += [_dataflash_fmt(10, "MAG", mag_fmt, mag_cols), _dataflash_fmt(11, "IMU", imu_fmt, imu_cols)]
    motor = "MOX" in mag_cols or "MOfsX" in mag_cols
    for k in range(len(run.t_s)):
        t_us = 1_000_000 + int(np.rint(run.t_s[k] * 1e6))
        stamp = [t_us // 1000] if time_field == "TimeMS" else [t_us]
        reading = np.round(run.mag_ut[k] * 10).astype(int)
        ofs = np.array(DATAFLASH_OFFSETS_MG) if "OfsX" in mag_cols else np.zeros(3, int)
        mot = np.array(DATAFLASH_MOTOR_MG) if motor else np.zeros(3, int)
        logged = (reading + ofs + mot).tolist()
        fields = [*logged, *ofs.tolist(), *mot.tolist()][: mag_fmt.count("h")] if "OfsX" in mag_cols else logged
        instance = [0] if ",I," in mag_cols else []
        tail = [1, t_us] if mag_fmt.endswith("BI") else []
        out.append(_dataflash_record(10, mag_fmt, [*stamp, *instance, *fields, *tail]))
        imu_values = [*run.gyr_rads[k].tolist(), *run.acc_ms2[k].tolist()]
        out.append(_dataflash_record(11, imu_fmt, [*stamp, *([0] if ",I," in imu_cols else []), *imu_values]))
    path.write_bytes(b"".join(out))
