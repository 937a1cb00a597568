"""MAVLink telemetry logs (``.tlog``: each message after its 8-byte reception time) as recorded inputs, read with
``pymavlink`` (see ``docs/autopilots.md``).

Magnetometer instance ``--mag N``: 0 is ``SCALED_IMU`` (else ``RAW_IMU``, else ``HIGHRES_IMU``), 1 ``SCALED_IMU2``,
2 ``SCALED_IMU3``; the field as the autopilot sent it (milligauss; gauss in HIGHRES_IMU), which may already be
corrected by the autopilot (ArduPilot sends its corrected field in RAW_IMU and SCALED_IMU2/3). Accelerometer and
gyroscope from the same message (milli-g and mrad/s; m/s^2 and rad/s in HIGHRES_IMU; RAW_IMU in ArduPilot's
scaling, the same as SCALED_IMU's). Only the messages of the vehicle (system id) that sent the first of them are
read. Times: the message's ``time_boot_ms`` / ``time_usec``; battery current (``SYS_STATUS.current_battery``, cA)
and throttle (``VFR_HUD.throttle``, %) carry no time of their own and are placed by their reception time, shifted
onto the vehicle's clock by the median difference between the two clocks over the IMU messages.
"""

from __future__ import annotations

import contextlib
import io
from collections import defaultdict
from pathlib import Path
from typing import Any

import numpy as np

from magnet.autopilot.mavlink import IMU_MESSAGES
from services.common.inputs.csvio import SampleTable
from services.common.inputs.flightlogs import LogStreams, ReferenceYaw, Stream, described, to_table
from services.common.inputs.input_options import InputOptions

IMU_TYPES = {0: ("SCALED_IMU", "RAW_IMU", "HIGHRES_IMU"), 1: ("SCALED_IMU2",), 2: ("SCALED_IMU3",)}
TYPES = ["SCALED_IMU", "RAW_IMU", "HIGHRES_IMU", "SCALED_IMU2", "SCALED_IMU3", "SYS_STATUS", "VFR_HUD", "ATTITUDE"]
#: (field unit in uT, accelerometer unit in m/s^2, gyroscope unit in rad/s) per message: MAVLink's own units, as
#: the live MAVLink source reads them (``magnet.autopilot.mavlink.IMU_MESSAGES``)
SCALES = {name: IMU_MESSAGES[name][1:4] for name in ("HIGHRES_IMU", "SCALED_IMU")}


def _messages(path: Path, types: list[str]) -> dict[str, list[Any]]:
    """The messages of ``types`` by name; ValueError naming the file when pymavlink cannot read it."""
    from pymavlink import mavutil

    if path.stat().st_size == 0:
        raise ValueError(f"{path}: the file is empty")
    found: dict[str, list[Any]] = defaultdict(list)
    quiet = io.StringIO()
    try:
        with contextlib.redirect_stdout(quiet), contextlib.redirect_stderr(quiet):
            log = mavutil.mavlink_connection(str(path), robust_parsing=True)
            try:
                while (message := log.recv_match(type=types)) is not None:
                    found[message.get_type()].append(message)
            finally:
                log.close()
    except Exception as exc:  # pymavlink raises whatever its parser meets in a damaged file
        raise ValueError(f"{path}: not a readable MAVLink telemetry log ({type(exc).__name__}: {exc})") from None
    return found


def _time_us(message: Any) -> float:
    """The message's time on the vehicle's clock, in microseconds."""
    if hasattr(message, "time_usec"):
        return float(message.time_usec)
    return float(message.time_boot_ms) * 1000.0


def _chosen(found: dict[str, list[Any]], path: Path, instance: int) -> tuple[str, list[Any]]:
    """(message name, its messages from one vehicle) for magnetometer ``instance``; ValueError when absent."""
    names = IMU_TYPES.get(instance, ())
    name = next((n for n in names if found.get(n)), None)
    if name is None:
        present = sorted(k for k, types in IMU_TYPES.items() if any(found.get(n) for n in types))
        if not present:
            raise ValueError(
                f"{path}: this log holds no magnetometer (no RAW_IMU, SCALED_IMU, SCALED_IMU2/3 or HIGHRES_IMU "
                "messages; not a MAVLink telemetry log, or the vehicle did not send them)"
            )
        raise ValueError(f"{path}: no magnetometer instance {instance} in this log (instances: {present}): use --mag")
    messages = found[name]
    system = messages[0].get_srcSystem()
    return name, [m for m in messages if m.get_srcSystem() == system]


def _streams(name: str, messages: list[Any]) -> tuple[Stream, Stream, Stream]:
    mag_scale, acc_scale, gyr_scale = SCALES.get(name, SCALES["SCALED_IMU"])
    t = np.array([_time_us(m) for m in messages])

    def vectors(prefix: str, suffix: str = "") -> np.ndarray:
        return np.array([[float(getattr(m, f"{a}{prefix}{suffix}")) for a in "xyz"] for m in messages])

    return (
        Stream(t, vectors("mag") * mag_scale),
        Stream(t, vectors("acc") * acc_scale),
        Stream(t, vectors("gyro") * gyr_scale),
    )


def _clock_offset_us(messages: list[Any]) -> float:
    """Median of (vehicle time - reception time) in microseconds over ``messages``."""
    return float(np.median([_time_us(m) - m._timestamp * 1e6 for m in messages]))


def _extra(found: dict[str, list[Any]], system: int, offset_us: float) -> tuple[dict[str, Stream], list[str]]:
    extra: dict[str, Stream] = {}
    words = []
    status = [m for m in found.get("SYS_STATUS", []) if m.get_srcSystem() == system]
    if status:
        t = np.array([m._timestamp * 1e6 + offset_us for m in status])
        current = np.array([float(m.current_battery) for m in status])
        extra["current_a"] = Stream(t, np.where(current < 0, np.nan, current / 100.0))
        words.append("SYS_STATUS current")
    hud = [m for m in found.get("VFR_HUD", []) if m.get_srcSystem() == system]
    if hud:
        t = np.array([m._timestamp * 1e6 + offset_us for m in hud])
        extra["throttle"] = Stream(t, np.clip(np.array([float(m.throttle) for m in hud]) / 100.0, 0.0, 1.0))
        words.append("VFR_HUD throttle")
    return extra, words


def read_tlog(path: Path, options: InputOptions) -> SampleTable:
    """The samples of a MAVLink telemetry log (see the module docstring); ValueError naming the file otherwise."""
    found = _messages(path, TYPES)
    instance = options.mag or 0
    name, messages = _chosen(found, path, instance)
    mag, acc, gyr = _streams(name, messages)
    system = messages[0].get_srcSystem()
    extra, words = _extra(found, system, _clock_offset_us(messages))
    note = (
        f"MAVLink telemetry: {name} of system {system} (magnetometer instance {instance}, the field as the "
        f"autopilot sent it); with {described([f'{name} accelerometer and gyroscope', *words])}"
    )
    return to_table(path, LogStreams(mag, acc, gyr, extra, note))


def tlog_reference_yaw(path: Path) -> ReferenceYaw:
    """The autopilot's attitude estimate in the log (``ATTITUDE.yaw``); ValueError when it was not sent."""
    found = _messages(path, ["ATTITUDE"])
    messages = found.get("ATTITUDE", [])
    if len(messages) < 2:
        raise ValueError(f"{path}: fewer than 2 ATTITUDE messages: no attitude estimate to compare with")
    system = messages[0].get_srcSystem()
    messages = [m for m in messages if m.get_srcSystem() == system]
    t = np.array([_time_us(m) for m in messages]) / 1e6
    yaw = np.mod(np.degrees([float(m.yaw) for m in messages]), 360.0)
    return ReferenceYaw(t, yaw, "ATTITUDE", "not in a telemetry log (the autopilot's own setting)")
