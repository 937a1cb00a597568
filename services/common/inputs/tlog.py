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

from pathlib import Path
from typing import Any

import numpy as np

from magnet.autopilot.mavlink import IMU_MESSAGES
from services.common.inputs import flightlogs
from services.common.inputs.csvio import SampleTable
from services.common.inputs.flightlogs import ReferenceYaw, Stream, Table
from services.common.inputs.input_options import InputOptions

IMU_TYPES = {0: ("SCALED_IMU", "RAW_IMU", "HIGHRES_IMU"), 1: ("SCALED_IMU2",), 2: ("SCALED_IMU3",)}
TYPES = ["SCALED_IMU", "RAW_IMU", "HIGHRES_IMU", "SCALED_IMU2", "SCALED_IMU3", "SYS_STATUS", "VFR_HUD", "ATTITUDE"]
#: (field unit in uT, accelerometer unit in m/s^2, gyroscope unit in rad/s) per message: MAVLink's own units, as
#: the live MAVLink source reads them (``magnet.autopilot.mavlink.IMU_MESSAGES``)
SCALES = {name: IMU_MESSAGES[name][1:4] for name in ("HIGHRES_IMU", "SCALED_IMU")}


#: the numbers kept of each message (system id, reception time s, vehicle time us, then its fields): a message is
#: reduced to them as it is read (a pymavlink message object is about a kilobyte), so memory follows what is kept
_IMU_FIELDS = tuple(f"{a}{kind}" for kind in ("mag", "acc", "gyro") for a in "xyz")
KEPT_FIELDS = dict.fromkeys(("SCALED_IMU", "RAW_IMU", "HIGHRES_IMU", "SCALED_IMU2", "SCALED_IMU3"), _IMU_FIELDS)
KEPT_FIELDS |= {"SYS_STATUS": ("current_battery",), "VFR_HUD": ("throttle",), "ATTITUDE": ("yaw",)}
HEAD = ("system", "received_s", "t_us")


def _row(message: Any, fields: tuple[str, ...]) -> list[float]:
    """The kept numbers of ``message`` (``HEAD`` and then ``fields``)."""
    head = [float(message.get_srcSystem()), float(message._timestamp), _time_us(message)]
    return head + [float(getattr(message, name)) for name in fields]


def _messages(path: Path, types: list[str]) -> dict[str, Table]:
    """The kept numbers of the messages of ``types`` by name; ValueError naming the file when pymavlink cannot read
    it."""
    if path.stat().st_size == 0:
        raise ValueError(f"{path}: the file is empty")
    found: dict[str, Table] = {}

    def take(message: Any) -> None:
        name = message.get_type()
        if name not in found:
            found[name] = Table((*HEAD, *KEPT_FIELDS[name]))
        found[name].add_row(_row(message, KEPT_FIELDS[name]))

    flightlogs.read_pymavlink(path, types, "MAVLink telemetry log", take, robust_parsing=True)
    return found


def _time_us(message: Any) -> float:
    """The message's time on the vehicle's clock, in microseconds (0 for a message that carries none)."""
    if hasattr(message, "time_usec"):
        return float(message.time_usec)
    return float(getattr(message, "time_boot_ms", 0)) * 1000.0


def _of_system(table: Table | None, system: int | None = None) -> Table | None:
    """The rows of ``table`` sent by ``system`` (default: the system of its first row); None when there are none."""
    if table is None or not len(table):
        return None
    systems = table.column("system")
    return table.where(systems == (systems[0] if system is None else system))


def _chosen(found: dict[str, Table], path: Path, instance: int) -> tuple[str, Table]:
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
    messages = _of_system(found[name])
    assert messages is not None  # found[name] is not empty
    return name, messages


def _streams(name: str, messages: Table) -> tuple[Stream, Stream, Stream]:
    mag_scale, acc_scale, gyr_scale = SCALES.get(name, SCALES["SCALED_IMU"])
    t = messages.column("t_us")

    def vectors(prefix: str) -> np.ndarray:
        return messages.columns(tuple(f"{a}{prefix}" for a in "xyz"))

    return (
        Stream(t, vectors("mag") * mag_scale),
        Stream(t, vectors("acc") * acc_scale),
        Stream(t, vectors("gyro") * gyr_scale),
    )


def _clock_offset_us(messages: Table) -> float:
    """Median of (vehicle time - reception time) in microseconds over ``messages``."""
    return float(np.median(messages.column("t_us") - messages.column("received_s") * 1e6))


def _extra(found: dict[str, Table], system: int, offset_us: float) -> tuple[dict[str, Stream], list[str]]:
    extra: dict[str, Stream] = {}
    words = []
    status = _of_system(found.get("SYS_STATUS"), system)
    if status is not None and len(status):
        t = status.column("received_s") * 1e6 + offset_us
        current = status.column("current_battery")
        extra["current_a"] = Stream(t, np.where(current < 0, np.nan, current / 100.0))
        words.append("SYS_STATUS current")
    hud = _of_system(found.get("VFR_HUD"), system)
    if hud is not None and len(hud):
        t = hud.column("received_s") * 1e6 + offset_us
        extra["throttle"] = Stream(t, np.clip(hud.column("throttle") / 100.0, 0.0, 1.0))
        words.append("VFR_HUD throttle")
    return extra, words


def read_tlog(path: Path, options: InputOptions) -> SampleTable:
    """The samples of a MAVLink telemetry log (see the module docstring); ValueError naming the file otherwise."""
    found = _messages(path, TYPES)
    instance = options.mag or 0
    name, messages = _chosen(found, path, instance)
    mag, acc, gyr = _streams(name, messages)
    system = int(messages.column("system")[0])
    extra, words = _extra(found, system, _clock_offset_us(messages))
    note = (
        f"MAVLink telemetry: {name} of system {system} (magnetometer instance {instance}, the field as the "
        f"autopilot sent it); with {flightlogs.described([f'{name} accelerometer and gyroscope', *words])}"
    )
    return flightlogs.to_table(path, flightlogs.LogStreams(mag, acc, gyr, extra, note))


def tlog_reference_yaw(path: Path) -> ReferenceYaw:
    """The autopilot's attitude estimate in the log (``ATTITUDE.yaw``); ValueError when it was not sent."""
    messages = _of_system(_messages(path, ["ATTITUDE"]).get("ATTITUDE"))
    if messages is None or len(messages) < 2:
        raise ValueError(f"{path}: fewer than 2 ATTITUDE messages: no attitude estimate to compare with")
    yaw = np.mod(np.degrees(messages.column("yaw")), 360.0)
    return ReferenceYaw(
        messages.column("t_us") / 1e6, yaw, "ATTITUDE", "not in a telemetry log (the autopilot's own setting)"
    )
