"""The samples of MAVLink vehicles as raw batches: one device per vehicle and magnetometer instance, times mapped
to the wire's clock, the vehicle's place, velocity, battery current and throttle attached. Pure: messages (dicts,
with ``sysid``) and the wall clock's ns come in, ``RawBatch`` lists come out (docs/mavlink.md).

Time. A vehicle stamps its messages with the time since it booted. The first message of a vehicle pins its boot time
to the wall clock (offset = now - boot); later messages keep that offset, so their intervals are the vehicle's. The
offset is set again (``resyncs``) when the vehicle's time goes back more than ``BACKWARDS_NS`` (a reboot, or the
32-bit millisecond counter wrapping after 49.7 days) or drifts from the wall clock by more than ``MAX_SKEW_NS``
(a vehicle that was silent, or whose clock runs off). Within a device times never go back: a sample is stamped at
least 1 ns after the one before it.

Attachments. A sample carries the vehicle's last velocity (GLOBAL_POSITION_INT), battery current (SYS_STATUS or
BATTERY_STATUS) and throttle (SERVO_OUTPUT_RAW) when they are at most ``FRESH_NS`` old (wall clock), NaN otherwise;
a batch carries the last place.

A gyroscope that reads zero. ArduPilot fills the gyroscope fields of SCALED_IMU2/3 with zeros when the compass has
no IMU of that number beside it. A reading of exactly zero on all three axes is kept only from a gyroscope that has
read anything else before (a real one at rest rounds to zero now and then); and one that keeps reading exactly zero
while the field turns by ``ZERO_GYRO_TURN_DEG`` is no gyroscope at all: its samples go out without one (the
compass and the calibrator then work from the field and the accelerometer), the device is listed in
``gyro_absent`` until it reads anything else.
"""

from __future__ import annotations

import collections
import dataclasses
import re
from collections.abc import Mapping
from typing import Any

import numpy as np

from magnet.autopilot import mavlink
from magnet.earth.location import Location
from magnet.wire.raw import RawBatch

SENSOR = "mavlink"
BACKWARDS_NS = 1_000_000_000
MAX_SKEW_NS = 2_000_000_000
FRESH_NS = 1_000_000_000
#: a device's samples wait at most this long (wall clock) before they go out in a short batch
MAX_WAIT_NS = 500_000_000
#: a gyroscope reading exactly zero all the while the field turns this far (deg) is absent
ZERO_GYRO_TURN_DEG = 30.0
#: the messages used besides the IMU ones
OTHER_MESSAGES = frozenset({"HEARTBEAT", "GLOBAL_POSITION_INT", "SYS_STATUS", "BATTERY_STATUS", "SERVO_OUTPUT_RAW"})
#: devices one connection may make by default (``--max-port-devices``): a port serves a vehicle or a few dozen, each
#: with up to three compasses; 255 system ids times 256 HIGHRES_IMU ids would be 65,280
MAX_PORT_DEVICES = 64


@dataclasses.dataclass
class Vehicle:
    """What is known of one vehicle (by MAVLink system id): the clock's offset, the last message (wall ns), its
    place, velocity, current and throttle with the wall ns each came, whether it is armed."""

    offset_ns: int | None = None
    last_boot_ns: int = 0
    last_seen_ns: int = 0
    location: Location | None = None
    velocity: tuple[np.ndarray, int] | None = None
    current: tuple[float, int] | None = None
    throttle: tuple[float, int] | None = None
    armed: bool = False


@dataclasses.dataclass
class GyroCheck:
    """Whether a device's gyroscope is there (module docstring): ``present`` once it read anything but exactly zero,
    ``absent`` once it read exactly zero while the field turned ``ZERO_GYRO_TURN_DEG`` from ``start`` (the field's
    direction, unit (3,), when the zeros began)."""

    present: bool = False
    absent: bool = False
    start: np.ndarray | None = None

    def usable(self, gyr_rads: np.ndarray | None, mag_ut: np.ndarray) -> bool:
        """Judge one sample's gyroscope (rad/s (3,), or None) with its field (uT (3,), not zero): whether to send
        it."""
        if gyr_rads is None:
            return False
        if gyr_rads.any():
            self.present, self.absent, self.start = True, False, None
            return True
        unit = mag_ut / float(np.linalg.norm(mag_ut))
        if self.start is None:
            self.start = unit
        elif float(unit @ self.start) < np.cos(np.radians(ZERO_GYRO_TURN_DEG)):
            self.present, self.absent = False, True
        return self.present


@dataclasses.dataclass
class Pending:
    """A device's samples not yet sent: times (ns) and rows of (mag (3), acc (3), gyr (3), vel (3), current,
    throttle)."""

    sysid: int
    times: list[int] = dataclasses.field(default_factory=list)
    rows: list[np.ndarray] = dataclasses.field(default_factory=list)
    first_ns: int = 0
    seq: int = 0
    last_t_ns: int = -1
    gyro: GyroCheck = dataclasses.field(default_factory=GyroCheck)


class MavlinkStream:
    """Turns the messages of any number of vehicles into raw batches of ``batch`` samples per device.

    ``feed(message, now_ns)`` takes one message (a dict of its fields with ``mavpackettype`` and ``sysid``);
    ``take(now_ns, flush)`` returns the batches due; ``health(now_ns, timeout_ns)`` says which devices' vehicles
    still send. ``counts`` holds ``messages``, ``samples``, ``ignored`` (types not used), ``resyncs`` and
    ``dropped:<cause>`` per cause; ``last_error`` the last drop's reason.

    At most ``max_devices`` devices: a sample of a new device beyond them is dropped and counted
    (``dropped:device-limit``); the devices already known are unaffected."""

    def __init__(self, prefix: str = "mav", batch: int = 10, motors: int = 4, max_devices: int = MAX_PORT_DEVICES):
        if isinstance(max_devices, bool) or not isinstance(max_devices, int) or max_devices < 1:
            raise ValueError(f"max_devices must be a whole number >= 1, got {max_devices!r}")
        self.prefix, self.batch, self.motors, self.max_devices = prefix, batch, motors, max_devices
        self.vehicles: dict[int, Vehicle] = {}
        self.pending: dict[str, Pending] = {}
        self.counts: collections.Counter[str] = collections.Counter()
        self.last_error = ""

    def device(self, sysid: int, instance: int) -> str:
        """The device id of a vehicle's magnetometer: ``<prefix><sysid>-mag<instance>``."""
        return f"{self.prefix}{sysid}-mag{instance}"

    def feed(self, message: Mapping[str, Any], now_ns: int) -> str | None:
        """Take one message; returns the cause when it was dropped (counted), else None."""
        self.counts["messages"] += 1
        kind = message.get("mavpackettype")
        if kind not in mavlink.IMU_MESSAGES and kind not in OTHER_MESSAGES:
            cause = "bad-data" if kind == "BAD_DATA" else None
            self.counts["dropped:bad-data" if cause else "ignored"] += 1
            if cause:
                self.last_error = "bytes that are not a MAVLink message"
            return cause
        sysid = message.get("sysid")
        if isinstance(sysid, bool) or not isinstance(sysid, int) or not 1 <= sysid <= 255:
            return self._drop("bad-field", f"{kind} from system id {sysid!r}, not 1..255")
        vehicle = self.vehicles.setdefault(sysid, Vehicle())
        try:
            self._use(kind, message, sysid, vehicle, now_ns)
        except mavlink.MavlinkError as exc:
            return self._drop(exc.cause, str(exc))
        vehicle.last_seen_ns = now_ns
        return None

    def _drop(self, cause: str, reason: str) -> str:
        self.counts[f"dropped:{cause}"] += 1
        self.last_error = reason
        return cause

    def _use(self, kind: str, message: Mapping[str, Any], sysid: int, vehicle: Vehicle, now_ns: int) -> None:
        if kind in mavlink.IMU_MESSAGES:
            self._sample(mavlink.imu_sample(message), sysid, vehicle, now_ns)
        elif kind == "GLOBAL_POSITION_INT":
            pos = mavlink.position(message)
            vehicle.location = pos.location or vehicle.location
            vehicle.velocity = (pos.vel_ned_ms, now_ns)
        elif kind in ("SYS_STATUS", "BATTERY_STATUS"):
            current = mavlink.battery_current_a(message)
            if current is not None:
                vehicle.current = (current, now_ns)
        elif kind == "SERVO_OUTPUT_RAW":
            value = mavlink.throttle(message, self.motors)
            if value is not None:
                vehicle.throttle = (value, now_ns)
        else:
            vehicle.armed = mavlink.armed(message)

    def _time(self, vehicle: Vehicle, boot_ns: int, now_ns: int) -> int:
        """Wall-clock ns of a vehicle's boot time (see the module docstring)."""
        off = vehicle.offset_ns
        if off is None or boot_ns < vehicle.last_boot_ns - BACKWARDS_NS or abs(boot_ns + off - now_ns) > MAX_SKEW_NS:
            if off is not None:
                self.counts["resyncs"] += 1
            vehicle.offset_ns = off = now_ns - boot_ns
            vehicle.last_boot_ns = boot_ns
        vehicle.last_boot_ns = max(boot_ns, vehicle.last_boot_ns)
        return boot_ns + off

    def _sample(self, sample: mavlink.ImuSample, sysid: int, vehicle: Vehicle, now_ns: int) -> None:
        device = self.device(sysid, sample.instance)
        pending = self.pending.get(device)
        if pending is None:
            if len(self.pending) >= self.max_devices:
                raise mavlink.MavlinkError(
                    "device-limit",
                    f"{device}: a new device beyond the {self.max_devices} this connection may make",
                )
            pending = self.pending[device] = Pending(sysid)
        t_ns = max(self._time(vehicle, sample.boot_ns, now_ns), pending.last_t_ns + 1)
        pending.last_t_ns = t_ns
        gyr = sample.gyr_rads if pending.gyro.usable(sample.gyr_rads, sample.mag_ut) else None
        if not pending.rows:
            pending.first_ns = now_ns
        nan3 = np.full(3, np.nan)
        row = np.concatenate(
            [
                sample.mag_ut,
                nan3 if sample.acc_ms2 is None else sample.acc_ms2,
                nan3 if gyr is None else gyr,
                _fresh(vehicle.velocity, now_ns, nan3),
                [_fresh(vehicle.current, now_ns, np.nan), _fresh(vehicle.throttle, now_ns, np.nan)],
            ]
        )
        pending.rows.append(row)
        pending.times.append(t_ns)
        self.counts["samples"] += 1

    def take(self, now_ns: int, flush: bool = False) -> list[RawBatch]:
        """The batches due: every device with ``batch`` samples waiting, or whose oldest waited ``MAX_WAIT_NS``
        (all of them when ``flush``)."""
        out = []
        for device, pending in self.pending.items():
            due = len(pending.rows) >= self.batch or now_ns - pending.first_ns >= MAX_WAIT_NS or flush
            while pending.rows and due:
                out.append(self._batch(device, pending))
                due = len(pending.rows) >= self.batch or flush
        return out

    def _batch(self, device: str, pending: Pending) -> RawBatch:
        rows, pending.rows = pending.rows[: self.batch], pending.rows[self.batch :]
        times, pending.times = pending.times[: self.batch], pending.times[self.batch :]
        table = np.array(rows)
        pending.seq += 1
        return RawBatch(
            device,
            pending.seq - 1,
            SENSOR,
            np.array(times, dtype=np.int64),
            table[:, 0:3],
            _columns(table[:, 3:6]),
            None,
            _columns(table[:, 6:9]),
            self.vehicles[pending.sysid].location,
            _columns(table[:, 9:12]),
            _values(table[:, 12]),
            _values(table[:, 13]),
        )

    @property
    def gyro_absent(self) -> list[str]:
        """The devices whose gyroscope reads exactly zero while their field turns (module docstring), sorted."""
        return sorted(d for d, p in self.pending.items() if p.gyro.absent)

    def health(self, now_ns: int, timeout_ns: int) -> dict[str, bool]:
        """Per device seen: whether its vehicle sent anything in the last ``timeout_ns``."""
        return {d: now_ns - self.vehicles[p.sysid].last_seen_ns <= timeout_ns for d, p in self.pending.items()}


def _fresh(value: tuple[Any, int] | None, now_ns: int, default: Any) -> Any:
    return default if value is None or now_ns - value[1] > FRESH_NS else value[0]


def _columns(block: np.ndarray) -> np.ndarray | None:
    """(N, 3) when every row is known, None when none is, rows of NaN left where some are (velocity)."""
    known = np.isfinite(block).all(axis=1)
    return None if not known.any() else block


def _values(column: np.ndarray) -> np.ndarray | None:
    return None if np.isnan(column).all() else column


def compass_instance(device: str | None) -> int | None:
    """The compass instance (0-based) a device id of ``MavlinkStream.device`` names (``mav1-mag2``: 2); None for an
    id of another form."""
    found = re.fullmatch(r"[A-Za-z0-9_]*\d+-mag(\d)", device or "")
    return int(found.group(1)) if found else None
