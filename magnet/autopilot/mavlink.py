"""MAVLink messages to magnet's units: one message (a dict of its fields, as pymavlink's ``to_dict`` gives) in, the
numbers magnet uses out. Pure: no sockets, no pymavlink import; the stream of a vehicle (time, batches, place) is
``magnet.autopilot.mavlink_stream``. Units and conventions: docs/mavlink.md.

- IMU messages (body frame, x forward, y right, z down, as magnet's):
  SCALED_IMU / SCALED_IMU2 / SCALED_IMU3 and RAW_IMU: mag in milligauss (0.1 uT), acceleration in milli-g, rate of
  turn in milliradians per second, time ``time_boot_ms`` (RAW_IMU ``time_usec``); instance 0, 1, 2 (RAW_IMU 0).
  HIGHRES_IMU: mag in gauss (100 uT), m/s^2, rad/s, ``time_usec``; instance its ``id`` (0 when absent).
- GLOBAL_POSITION_INT: lat/lon in 1e-7 deg, alt in mm above mean sea level, vx/vy/vz in cm/s north-east-down,
  ``time_boot_ms``; lat = lon = 0 means no fix.
- SYS_STATUS ``current_battery`` and BATTERY_STATUS ``current_battery`` (battery ``id`` 0): centiamperes, -1 when not
  measured. SERVO_OUTPUT_RAW ``servoN_raw``: pulse widths in microseconds, 1000 idle to 2000 full.
- HEARTBEAT ``base_mode`` bit 128 (MAV_MODE_FLAG_SAFETY_ARMED): the vehicle is armed.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping
from typing import Any

import numpy as np

from magnet.earth.location import Location
from magnet.units import STANDARD_GRAVITY_MS2, UT_PER_GAUSS, UT_PER_MGAUSS

MS2_PER_MILLI_G = STANDARD_GRAVITY_MS2 / 1000.0
ARMED_FLAG = 128  # MAV_MODE_FLAG_SAFETY_ARMED
#: the IMU messages: name -> (instance, field scale uT, acc scale m/s^2, gyro scale rad/s, time field, ns per tick)
IMU_MESSAGES: dict[str, tuple[int | None, float, float, float, str, int]] = {
    "RAW_IMU": (0, UT_PER_MGAUSS, MS2_PER_MILLI_G, 1e-3, "time_usec", 1_000),
    "SCALED_IMU": (0, UT_PER_MGAUSS, MS2_PER_MILLI_G, 1e-3, "time_boot_ms", 1_000_000),
    "SCALED_IMU2": (1, UT_PER_MGAUSS, MS2_PER_MILLI_G, 1e-3, "time_boot_ms", 1_000_000),
    "SCALED_IMU3": (2, UT_PER_MGAUSS, MS2_PER_MILLI_G, 1e-3, "time_boot_ms", 1_000_000),
    "HIGHRES_IMU": (None, UT_PER_GAUSS, 1.0, 1.0, "time_usec", 1_000),
}
#: HIGHRES_IMU ``fields_updated`` bits of the magnetometer's x, y, z
HIGHRES_MAG_BITS = 0b111 << 6
#: beyond these a message is not a magnetometer, an accelerometer or a gyroscope on Earth (as the wire's limits)
MAX_FIELD_UT, MAX_ACC_MS2, MAX_GYR_RADS = 5_000.0, 2_000.0, 100.0
PWM_IDLE_US, PWM_FULL_US = 1000.0, 2000.0


class MavlinkError(ValueError):
    """A message magnet cannot use; ``cause`` is one word it is counted by."""

    def __init__(self, cause: str, message: str) -> None:
        super().__init__(message)
        self.cause = cause


@dataclasses.dataclass(frozen=True)
class ImuSample:
    """One IMU message: instance (0, 1, 2 ...), boot_ns (ns since the vehicle booted), mag_ut (3,) uT, acc_ms2 (3,)
    m/s^2 and gyr_rads (3,) rad/s (None where the message has none), all body frame FRD."""

    instance: int
    boot_ns: int
    mag_ut: np.ndarray
    acc_ms2: np.ndarray | None
    gyr_rads: np.ndarray | None


@dataclasses.dataclass(frozen=True)
class Position:
    """GLOBAL_POSITION_INT: boot_ns, location (None without a fix), vel_ned_ms (3,) m/s NED (NaN without a fix)."""

    boot_ns: int
    location: Location | None
    vel_ned_ms: np.ndarray


def _number(message: Mapping[str, Any], name: str) -> float:
    value = message.get(name)
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        raise MavlinkError("bad-field", f"{message.get('mavpackettype')}.{name} must be a finite number, got {value!r}")
    return float(value)


def _vector(message: Mapping[str, Any], names: tuple[str, str, str], scale: float, limit: float) -> np.ndarray:
    arr = np.array([_number(message, n) for n in names]) * scale
    if np.abs(arr).max() > limit:
        raise MavlinkError("absurd-magnitude", f"{message.get('mavpackettype')} {names[0][1:]} beyond +-{limit:g}")
    return arr


def _time_ns(message: Mapping[str, Any], field: str, ns_per_tick: int) -> int:
    value = message.get(field)
    if isinstance(value, bool) or not isinstance(value, int) or value < 0:
        raise MavlinkError("bad-field", f"{message.get('mavpackettype')}.{field} must be a whole number >= 0")
    return value * ns_per_tick


def imu_sample(message: Mapping[str, Any]) -> ImuSample:
    """The IMU sample of an IMU message (``IMU_MESSAGES``); MavlinkError when its numbers are unusable."""
    instance, mag_scale, acc_scale, gyr_scale, time_field, ns_per_tick = IMU_MESSAGES[message["mavpackettype"]]
    if instance is None:  # HIGHRES_IMU: the id extension names the instance; its mag must be among the fields updated
        instance = int(message.get("id") or 0)
        updated = message.get("fields_updated")
        if isinstance(updated, int) and updated and not updated & HIGHRES_MAG_BITS:
            raise MavlinkError("no-mag", "HIGHRES_IMU without a new magnetometer reading")
    mag = _vector(message, ("xmag", "ymag", "zmag"), mag_scale, MAX_FIELD_UT)
    acc = _vector(message, ("xacc", "yacc", "zacc"), acc_scale, MAX_ACC_MS2)
    gyr = _vector(message, ("xgyro", "ygyro", "zgyro"), gyr_scale, MAX_GYR_RADS)
    if not mag.any():
        raise MavlinkError("no-mag", f"{message['mavpackettype']} with a zero field (no magnetometer)")
    return ImuSample(instance, _time_ns(message, time_field, ns_per_tick), mag, None if not acc.any() else acc, gyr)


def position(message: Mapping[str, Any]) -> Position:
    """GLOBAL_POSITION_INT as a place and a velocity; MavlinkError when its numbers are unusable."""
    lat, lon = _number(message, "lat") * 1e-7, _number(message, "lon") * 1e-7
    vel = np.array([_number(message, n) for n in ("vx", "vy", "vz")]) * 0.01
    boot_ns = _time_ns(message, "time_boot_ms", 1_000_000)
    if lat == 0.0 and lon == 0.0:
        return Position(boot_ns, None, np.full(3, np.nan))
    try:
        location = Location(lat, lon, _number(message, "alt") * 1e-3)
    except ValueError as exc:
        raise MavlinkError("bad-location", f"GLOBAL_POSITION_INT: {exc}") from None
    return Position(boot_ns, location, vel)


def battery_current_a(message: Mapping[str, Any]) -> float | None:
    """SYS_STATUS or BATTERY_STATUS (battery 0) current in A, None when not measured or another battery's."""
    if message["mavpackettype"] == "BATTERY_STATUS" and int(message.get("id") or 0) != 0:
        return None
    centiamps = _number(message, "current_battery")
    return None if centiamps == -1 else centiamps * 0.01


def throttle(message: Mapping[str, Any], motors: int) -> float | None:
    """SERVO_OUTPUT_RAW: the mean of the first ``motors`` outputs mapped from 1000..2000 us to 0..1 (outputs at 0,
    unused, left out); None when none is in use."""
    pulses = [_number(message, f"servo{i}_raw") for i in range(1, motors + 1)]
    used = [p for p in pulses if 0 < p < 65535]
    if not used:
        return None
    fractions = [(p - PWM_IDLE_US) / (PWM_FULL_US - PWM_IDLE_US) for p in used]
    return float(np.clip(np.mean(fractions), 0.0, 1.0))


def armed(message: Mapping[str, Any]) -> bool:
    """HEARTBEAT: whether the vehicle is armed."""
    return bool(int(_number(message, "base_mode")) & ARMED_FLAG)


def message_dict(message: Any) -> dict[str, Any]:
    """A parsed MAVLink message (pymavlink's message object: ``to_dict`` and ``get_srcSystem``) as the dict this
    module reads: its fields, ``mavpackettype``, ``sysid`` and ``compid``."""
    out = dict(message.to_dict())
    out["sysid"] = message.get_srcSystem()
    out["compid"] = message.get_srcComponent()
    return out
